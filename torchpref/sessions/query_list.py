r"""A session's fixed list of candidate queries (``PreferenceSession(queries=...)``).

A study may have its questions already (pre-planned trajectories, a stimulus set's pairs): the
session then asks, at each step, the query its selector chooses among those not yet answered
(:meth:`~torchpref.selection.strategies.Selector.choose`; all of them again once every one is
answered). The queries' items are rows of the session's pool; the header records each query as
its kind and pool rows (``"queries"``), so a resumed session asks from the same list.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import torch
from torch import Tensor

from torchpref.data.files import read_regular_text
from torchpref.data.queries import Query, RankingQuery, RatingQuery
from torchpref.sessions.errors import SessionFileError, SessionMismatchError
from torchpref.sessions.records import SessionHeader

__all__ = [
    "read_question_list",
    "check_pool_rows",
    "pool_rows_of",
    "queries_of_spec",
    "resumed_queries",
]

QuerySpec = list[list]  # [[kind, row, row, ...], ...]


def pool_rows_of(queries: Sequence[Query], pool: Tensor) -> QuerySpec:
    """Each query as ``[kind, pool rows...]``: its items found among the rows of ``pool`` (``N x d``,
    the first equal row).

    Raises:
        ValueError: an empty list, something not a query, or an item that is not a pool row (naming
            the query).
    """
    if isinstance(queries, (RatingQuery, RankingQuery)) or len(queries) == 0:
        raise ValueError(f"queries must be a non-empty list of RatingQuery / RankingQuery, got {queries!r:.80}.")
    spec: QuerySpec = []
    for i, q in enumerate(queries):
        if not isinstance(q, (RatingQuery, RankingQuery)):
            raise ValueError(f"queries[{i}] is not a RatingQuery or RankingQuery: {q!r:.80}.")
        items = torch.as_tensor(q.items).to(pool)
        if items.dim() != 2 or items.shape[-1] != pool.shape[-1]:
            raise ValueError(f"queries[{i}] has items of shape {tuple(items.shape)}, not m x {pool.shape[-1]}.")
        match = (items.unsqueeze(1) == pool.unsqueeze(0)).all(-1)  # m x N
        if not bool(match.any(-1).all()):
            raise ValueError(f"queries[{i}] shows an item that is not one of the session's candidates.")
        rows = [int(r) for r in match.to(torch.int8).argmax(-1)]
        if len(set(rows)) != len(rows):
            raise ValueError(f"queries[{i}] shows one item twice.")
        spec.append([q.kind, *rows])
    return spec


def queries_of_spec(spec: QuerySpec, pool: Tensor) -> list[Query]:
    """The queries of a header's ``"queries"`` (``[kind, rows...]`` each), items from ``pool``, with
    their pool rows as ``index`` / ``indices``."""
    out: list[Query] = []
    for kind, *rows in spec:
        if kind == "rating" and len(rows) == 1:
            out.append(RatingQuery(pool[rows[0]], int(rows[0])))
        elif kind == "ranking" and len(rows) >= 2:
            out.append(RankingQuery(pool[rows], tuple(int(r) for r in rows)))
        else:
            raise ValueError(
                f"a recorded query must be ['rating', row] or ['ranking', row, row, ...], got {spec!r:.80}."
            )
    return out


def resumed_queries(header: SessionHeader, given: bool, mine: QuerySpec | None, path: object) -> QuerySpec | None:
    """A resumed file's query list: the header's; queries given (``mine``) must be the same.

    Raises:
        SessionMismatchError: queries given that are not the file's.
    """
    theirs = header.queries
    if given and theirs != mine:
        raise SessionMismatchError(
            f"session file {path} was written with {'other' if theirs else 'no'} candidate queries; "
            f"open it with PreferenceSession.load({str(path)!r}) to use the file's.",
            "queries",
            str(theirs)[:80],
            str(mine)[:80],
        )
    return theirs


def check_pool_rows(pool: Tensor | None, items: Tensor, rows: list[int]) -> None:
    """``items`` are the rows ``rows`` of the session's pool (checked before the model is touched;
    the file's format checks it again), else a ``ValueError``."""
    if pool is None or not all(0 <= i < pool.shape[0] for i in rows) or not torch.equal(pool[rows].to(items), items):
        raise ValueError(
            f"the query's items are not this session's pool rows {rows}: a query of another "
            "session, or one edited after ask()."
        )


def read_question_list(path: str | os.PathLike[str], X: Tensor) -> list[Query]:
    """The questions of a question-list file (``elicit``'s and ``serve``'s ``--question-list``):
    per line, comma-separated 0-based rows of ``X`` (one: a rating, several: a best-of); blank
    lines and lines starting with ``#`` are skipped.

    Raises:
        FileNotFoundError: no such file.
        SessionFileError: not a regular file (a FIFO is refused without blocking), too large, or a
            line that is not distinct row numbers of ``X`` (naming it).
    """
    try:
        text = read_regular_text(path, "question list", max_bytes=8 * 2**20)
    except ValueError as err:
        raise SessionFileError(str(err)) from None
    out: list[Query] = []
    for n, line in enumerate(text.splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            rows = [int(t) for t in line.replace(";", ",").split(",") if t.strip()]
            if not rows or not all(0 <= r < X.shape[0] for r in rows) or len(set(rows)) != len(rows):
                raise ValueError
        except ValueError:
            raise SessionFileError(
                f"{path} line {n}: {line.strip()!r:.60} is not distinct row numbers 0..{X.shape[0] - 1}."
            ) from None
        out.append(RatingQuery(X[rows[0]]) if len(rows) == 1 else RankingQuery(X[rows]))
    if not out:
        raise SessionFileError(f"{path} lists no questions.")
    return out
