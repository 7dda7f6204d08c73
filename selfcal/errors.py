"""The errors a user can cause (bad input, data that cannot determine the model): the CLI reports them in
one line and exits 1.  Anything else is a bug and keeps its traceback."""
from selfcal.core.solve import DegenerateDataError
from selfcal.io.recording import RecordingError
from selfcal.core.static_intervals import StaticDetectionError, TooFewStaticPosesError
from selfcal.core.sphere import SphereNotFoundError
from selfcal.io.pointcloud_errors import PointCloudError
from selfcal.pipelines.qc.spec import QCSpecError
from selfcal.pipelines.fleet import FleetError
from selfcal.io.streams import StreamError
from selfcal.pipelines.track import TrackError

USER_ERRORS = (RecordingError, DegenerateDataError, TooFewStaticPosesError, StaticDetectionError, FileNotFoundError, FileExistsError,
               NotADirectoryError, PermissionError, SphereNotFoundError, PointCloudError, QCSpecError, FleetError,
               StreamError, TrackError)
