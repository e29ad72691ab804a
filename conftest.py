"""Every test run gets its own ROS domain and single-threaded BLAS before rclpy is imported,
and Ctrl-C as a terminal has it."""
import os
import signal

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('OMP_NUM_THREADS', '1')
os.environ.setdefault('MPLBACKEND', 'Agg')

from coop_common.testing import isolate_ros_environment  # noqa: E402

isolate_ros_environment(int(os.environ['COOP_TEST_DOMAIN_ID'])
                        if 'COOP_TEST_DOMAIN_ID' in os.environ else None)

# A run started in the background of a non-interactive shell (a CI runner, `cmd &`) inherits
# SIGINT ignored, and every process it starts inherits that: `ros2 launch` would then ignore
# the Ctrl-C a test sends it, and never escalate to SIGTERM / SIGKILL for a node that hangs.
# Tests send Ctrl-C as a terminal does, to processes that handle it as a terminal's would.
signal.signal(signal.SIGINT, signal.default_int_handler)
