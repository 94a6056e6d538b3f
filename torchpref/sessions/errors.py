r"""Every error and warning of a session, in one place (the one export list of
:mod:`torchpref.sessions`): a file that cannot be used (:class:`SessionFileError` and its kinds),
and the warning of a repaired file. An invalid *answer* is
:class:`~torchpref.data.queries.InvalidAnswer`, raised by the queries' validation."""

from __future__ import annotations

__all__ = [
    "SessionFileChanged",
    "SessionFileCorrupt",
    "SessionFileError",
    "SessionFileGone",
    "SessionForkError",
    "SessionMismatchError",
    "SessionReadOnlyError",
    "SessionRepairWarning",
    "SessionSettingsError",
    "SessionVersionError",
]


class SessionFileError(ValueError):
    """A session file that cannot be used as it is (the message names the file and line)."""


class SessionFileCorrupt(SessionFileError):
    """A line of a session file is incomplete or not a JSON record.

    Attributes:
        path: the file.
        line_number: the 1-based number of the bad line.
        reason: what is wrong with it.
        repairable: whether ``repair=True`` can fix it (only a bad *last* line: a crash
            mid-write; a bad line followed by good ones is never dropped).
        partial: the bad line's bytes.
        offset: the byte offset where the bad line starts.
    """

    def __init__(self, path: object, line_number: int, reason: str, repairable: bool, partial: bytes, offset: int):
        self.path, self.line_number, self.reason = str(path), line_number, reason
        self.repairable, self.partial, self.offset = repairable, partial, offset
        fix = (
            "It looks like a crash in the middle of writing the last answer. To recover, open it with "
            "repair=True (PreferenceSession(..., repair=True) or PreferenceSession.load(path, repair=True)): "
            f"the partial line is moved to {self.path}.dropped, the file is truncated to its last complete "
            "record, and that answer is asked again."
            if repairable
            else "The lines after it are valid, so this is not an interrupted write; the file was edited or "
            "damaged and must be fixed by hand."
        )
        super().__init__(f"session file {self.path}, line {line_number}: {reason}. {fix}")


class SessionVersionError(SessionFileError):
    """The file was written by a newer format version than this library reads."""


class SessionMismatchError(SessionFileError):
    """The file was written for other items, dimensions or settings than those given.

    Attributes:
        setting: the header field that differs (``"dim"``, ``"candidates"``, ``"bounds"``, ...).
        theirs: the file's value, described.
        mine: the value given, described.
    """

    def __init__(self, message: str, setting: str = "", theirs: str = "", mine: str = ""):
        super().__init__(message)
        self.setting, self.theirs, self.mine = setting, theirs, mine


class SessionRepairWarning(UserWarning):
    """A partial last line was removed from a session file (``repair=True``)."""


class SessionFileGone(SessionFileError):
    """The session file was deleted, moved away or replaced while the session had it open."""


class SessionFileChanged(SessionFileError):
    """Another program shortened, extended or rewrote the open session file in place (an editor,
    ``rsync --inplace``): its bytes are no longer the records this session acknowledged, so
    nothing more is written after them."""


class SessionForkError(SessionFileError):
    """A forked child process tried to write to its parent's session."""


class SessionReadOnlyError(SessionFileError):
    """The session file was opened read-only (the process may not write it): answers are refused."""


class SessionSettingsError(SessionMismatchError):
    """A session file records a model or selector this session does not reproduce (``setting`` is
    ``"model"`` or ``"selector"``)."""
