"""Fixtures of the ``torchpref serve`` tests run in process (Starlette's test client)."""

import pytest

from torchpref.testing.serve import random_items, serve_client


@pytest.fixture
def served(tmp_path):
    """A store of 24 random items (8 questions a session), its client, and one new session's id."""
    pytest.importorskip("starlette", reason="the serve extra (starlette) is not installed")
    pytest.importorskip("httpx", reason="starlette's test client needs httpx")
    from torchpref.frontends.serve.store import SessionStore
    from torchpref.selection.strategies import UCBC

    # UCBC: these tests need both kinds of question (the default asks ratings almost only)
    store = SessionStore(random_items(), tmp_path / "sessions", num_queries=8, selector=UCBC(m=5))
    client = serve_client(store)
    sid = client.post("/api/new", json={}).json()["sid"]
    yield store, client, sid
    store.close()
