"""The UCI Forest Fires data (Cortez & Morais 2007, CC BY 4.0): where to find it, how to fetch it, and the
features the linear regression uses.

Found by, in order: an explicit path (--data), $NAC_DATA_DIR/forestfires.csv, the user cache
($XDG_CACHE_HOME or ~/.cache)/nac/forestfires.csv, which `nac-onboard data fetch` fills from the UCI archive
after checking the CSV's sha256, then, in a source checkout, `../shared/data` beside it (what `make` passes as
$NAC_DATA_DIR, so a command run by hand finds what `make demo` found).

Features (30 columns): an intercept; X, Y, FFMC, DMC, DC, ISI, temp, RH, wind and rain standardised (mean 0,
population standard deviation 1, over all 517 rows); month and day one-hot (12 + 7 columns, jan..dec, mon..sun).
Target: log(1 + area), area in hectares.
"""

from __future__ import annotations

import csv
import hashlib
import io
import math
import os
import urllib.request
import zipfile
from pathlib import Path

import numpy as np

from nac_onboard.errors import BadInput, OperationFailed

CSV_NAME = "forestfires.csv"
CSV_SHA256 = "0d6586a1fa52f55bef48578aef14eb97273f1e9330e1a53423df497a77065253"
UCI_ARCHIVE_URL = "https://archive.ics.uci.edu/static/public/162/forest+fires.zip"
COLUMNS = ["X", "Y", "month", "day", "FFMC", "DMC", "DC", "ISI", "temp", "RH", "wind", "rain", "area"]
NUMERIC = ["X", "Y", "FFMC", "DMC", "DC", "ISI", "temp", "RH", "wind", "rain"]
MONTHS = ["jan", "feb", "mar", "apr", "may", "jun", "jul", "aug", "sep", "oct", "nov", "dec"]
DAYS = ["mon", "tue", "wed", "thu", "fri", "sat", "sun"]
#: What each column can be (UCI's description of the data set, with room): a value outside is a damaged file.
DOMAIN = {"X": (1, 9), "Y": (1, 9), "FFMC": (0, 101), "DMC": (0, 1000), "DC": (0, 2000), "ISI": (0, 100),
          "temp": (-60, 60), "RH": (0, 100), "wind": (0, 100), "rain": (0, 500), "area": (0, 1e5)}
FEATURES = ["intercept", *NUMERIC, *(f"month_{m}" for m in MONTHS), *(f"day_{d}" for d in DAYS)]


class DataError(BadInput):
    """The data set is missing or malformed; the message says where it looked or which line is wrong."""


class DownloadError(OperationFailed):
    """The archive could not be fetched or was not the one expected: the network's fault, not the input's (exit 1)."""


SOURCE_CHECKOUT_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"  # ../shared/data of a checkout


def cache_dir() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "nac"


def find_csv(explicit: str | None = None) -> Path:
    candidates = []
    if explicit:
        candidates.append(Path(explicit))
    elif os.environ.get("NAC_DATA_DIR"):
        candidates.append(Path(os.environ["NAC_DATA_DIR"]) / CSV_NAME)
    candidates += [cache_dir() / CSV_NAME, SOURCE_CHECKOUT_DATA / CSV_NAME]
    for path in candidates[:1] if explicit else candidates:
        if path.is_file():
            return path
    looked = ", ".join(str(p) for p in (candidates[:1] if explicit else candidates))
    raise DataError(f"Forest Fires CSV not found (looked in {looked}); run `nac-onboard data fetch`, set "
                    f"NAC_DATA_DIR to its folder, or pass --data FILE")


def fetch(url: str = UCI_ARCHIVE_URL, dest_dir: Path | None = None, timeout_s: float = 60.0) -> Path:
    """Download the UCI archive, take forestfires.csv out of it, check its sha256 and store it in the cache."""
    dest = (dest_dir or cache_dir()) / CSV_NAME
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as response:
            archive = response.read()
    except OSError as err:
        raise DownloadError(f"cannot download {url}: {err}") from None
    try:
        with zipfile.ZipFile(io.BytesIO(archive)) as z:
            name = next((n for n in z.namelist() if n.rsplit("/", 1)[-1] == CSV_NAME), None)
            if name is None:
                raise DownloadError(f"{url}: the archive has no {CSV_NAME}")
            data = z.read(name)
    except zipfile.BadZipFile:
        raise DownloadError(f"{url}: not a zip archive") from None
    digest = hashlib.sha256(data).hexdigest()
    if digest != CSV_SHA256:
        raise DownloadError(f"{url}: {CSV_NAME} has sha256 {digest}, expected {CSV_SHA256}; not stored")
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_suffix(".part")
    tmp.write_bytes(data)
    tmp.replace(dest)
    return dest


def load(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Features X (rows x 30) and target y = log(1 + area) from the CSV, checked line by line."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise DataError(f"cannot read {path}: {err}") from None
    rows = list(csv.reader(text.splitlines()))
    if not rows or rows[0] != COLUMNS:
        raise DataError(f"{path}: line 1: expected the header {','.join(COLUMNS)}")
    numeric, months, days, area = [], [], [], []
    for line, row in enumerate(rows[1:], start=2):
        if len(row) != len(COLUMNS):
            raise DataError(f"{path}: line {line}: expected {len(COLUMNS)} fields, got {len(row)}")
        record = dict(zip(COLUMNS, row, strict=True))
        if record["month"] not in MONTHS or record["day"] not in DAYS:
            raise DataError(f"{path}: line {line}: unknown month or day {record['month']!r}, {record['day']!r}")
        values = {}
        for column in (*NUMERIC, "area"):
            low, high = DOMAIN[column]
            try:
                value = float(record[column])
            except ValueError:
                raise DataError(f"{path}: line {line}: {column} {record[column]!r} is not a number") from None
            if not (math.isfinite(value) and low <= value <= high):
                raise DataError(f"{path}: line {line}: {column} {record[column]!r} outside {low:g}..{high:g} "
                                f"(the data set's domain)")
            values[column] = value
        numeric.append([values[c] for c in NUMERIC])
        area.append(values["area"])
        months.append(MONTHS.index(record["month"]))
        days.append(DAYS.index(record["day"]))
    if not numeric:
        raise DataError(f"{path}: no data rows")
    values = np.array(numeric)
    std = values.std(axis=0)
    standardised = (values - values.mean(axis=0)) / np.where(std > 0, std, 1.0)
    n = len(values)
    x = np.hstack([np.ones((n, 1)), standardised, np.eye(12)[months], np.eye(7)[days]])
    return x, np.log1p(np.array(area))
