"""``torchpref elicit --question-list FILE``: row numbers become rating and best-of queries; bad
lines are refused by line number."""

import pytest
import torch

from torchpref.data.queries import RankingQuery, RatingQuery
from torchpref.frontends.elicit import question_list
from torchpref.sessions.errors import SessionFileError


def test_rows_become_queries_and_bad_lines_are_named(tmp_path):
    X = torch.rand(5, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    f = tmp_path / "q.txt"
    f.write_text("# pairs and a rating\n0, 3\n\n1,2,4\n2\n")
    qs = question_list(str(f), X)
    assert [type(q) for q in qs] == [RankingQuery, RankingQuery, RatingQuery]
    assert torch.equal(qs[1].items, X[[1, 2, 4]]) and torch.equal(qs[2].item, X[2])
    assert question_list(None, X) is None
    for bad in ("0,5\n", "1,1\n", "a,b\n", "# none\n"):
        f.write_text(bad)
        with pytest.raises(SessionFileError, match="q.txt"):
            question_list(str(f), X)
