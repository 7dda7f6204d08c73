"""selfcal: instrument self-calibration and sensor fusion as GTSAM factor graphs, with a residual audit."""
import os

# The dense algebra here is small (hundreds of rows): BLAS threads only contend with GTSAM's own threads and
# made a 340x85 least-squares solve 100x slower on a busy 2-core machine.  Respect an explicit user setting.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
