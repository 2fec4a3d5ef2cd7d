"""A run's records: the run directory's layout and every record kind, the one place they are named.

    from nac_onboard.records import kinds
    log.write(kinds.TELEMETRY, sysid=1, ...)        # a writer (nac_onboard.flight_log.JsonlLog)
    read_jsonl(path).of_kind(kinds.ITERATION)       # a reader

`kinds.py` defines each file and kind once (fields, units, optional ones); `schema.py` what a definition is and how
writers are checked; `docs.py` makes docs/records.md from them.
"""

from nac_onboard.records.schema import READABLE_VERSIONS, SCHEMA_VERSION, Field, Kind, RunFile

__all__ = ["READABLE_VERSIONS", "SCHEMA_VERSION", "Field", "Kind", "RunFile"]
