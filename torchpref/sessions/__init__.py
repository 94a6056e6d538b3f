"""A person's session: the durable journal of answers, its records and settings."""

from __future__ import annotations

from torchpref.sessions.contents import (
    SessionContents,
    read_session,
    read_session_header,
)
from torchpref.sessions.errors import (
    SessionFileChanged,
    SessionFileCorrupt,
    SessionFileError,
    SessionFileGone,
    SessionForkError,
    SessionMismatchError,
    SessionReadOnlyError,
    SessionRepairWarning,
    SessionSettingsError,
    SessionVersionError,
)
from torchpref.sessions.journal import (
    MAX_FILE_BYTES,
    Journal,
    MemoryJournal,
    read_header,
    read_session_file,
)
from torchpref.sessions.recorded import (
    describe_model,
    describe_selector,
)
from torchpref.sessions.records import (
    ANSWER_KINDS,
    FORMAT_VERSION,
    SessionHeader,
    check_new_record,
    dumps_settings,
    records_in_force,
    validate_header,
    validate_records,
)
from torchpref.sessions.session import (
    PreferenceSession,
)
from torchpref.sessions.settings import (
    MAX_REDRAWS,
    SessionAnswer,
    SessionSettings,
    as_items,
    default_ranking_size,
    default_session_model,
    step_generator,
)

__all__ = [
    'ANSWER_KINDS',
    'FORMAT_VERSION',
    'Journal',
    'MAX_FILE_BYTES',
    'MAX_REDRAWS',
    'MemoryJournal',
    'PreferenceSession',
    'SessionAnswer',
    'SessionContents',
    'SessionFileCorrupt',
    'SessionFileError',
    'SessionFileChanged',
    'SessionFileGone',
    'SessionForkError',
    'SessionHeader',
    'SessionMismatchError',
    'SessionReadOnlyError',
    'SessionRepairWarning',
    'SessionSettings',
    'SessionSettingsError',
    'SessionVersionError',
    'as_items',
    'check_new_record',
    'default_ranking_size',
    'default_session_model',
    'describe_model',
    'describe_selector',
    'dumps_settings',
    'read_header',
    'read_session',
    'read_session_file',
    'read_session_header',
    'records_in_force',
    'step_generator',
    'validate_header',
    'validate_records',
]
