"""Where the shared real datasets are: ``$SELFCAL_SHARED_DATA``, else ``../shared/data`` beside the checkout, else
the workplace's ``/work/shared/data`` (so a scratch clone elsewhere still finds them).  Tests that need one skip
without it, saying where they looked."""
import os
from pathlib import Path


def _shared_data() -> Path:
    if os.environ.get("SELFCAL_SHARED_DATA"):
        return Path(os.environ["SELFCAL_SHARED_DATA"])
    beside = Path(__file__).resolve().parents[2] / "shared" / "data"
    return beside if beside.is_dir() else Path("/work/shared/data")


SHARED_DATA = _shared_data()
