"""The reply a request gets when nothing is recorded: :class:`AnswerRefused` and its HTTP status
(shared by the session store and the session pool of ``torchpref serve``)."""

from __future__ import annotations

__all__ = ["AnswerRefused"]


class AnswerRefused(ValueError):
    """A request that is not recorded; ``status`` is the HTTP status (400 invalid, 404 no such
    session, 409 stale or foreign question) and ``state`` the session's current state, if any."""

    def __init__(self, message: str, status: int = 400, state: dict | None = None):
        super().__init__(message)
        self.status, self.state = status, state
