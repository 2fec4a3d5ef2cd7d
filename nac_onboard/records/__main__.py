"""Write docs/records.md from the record definitions, or with --check say whether it is up to date (exit 1)."""

import sys
from pathlib import Path

from nac_onboard.records.docs import markdown

DOC = Path(__file__).resolve().parents[2] / "docs" / "records.md"

if "--check" in sys.argv[1:]:
    if not DOC.exists() or DOC.read_text() != markdown():
        sys.exit(f"{DOC} is not what nac_onboard/records/kinds.py says: run python -m nac_onboard.records")
else:
    DOC.write_text(markdown())
    print(f"wrote {DOC}")
