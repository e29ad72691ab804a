"""Every test run gets its own ROS domain and single-threaded BLAS before rclpy is imported."""
import os

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('OMP_NUM_THREADS', '1')
os.environ.setdefault('MPLBACKEND', 'Agg')

from coop_common.testing import isolate_ros_environment  # noqa: E402

isolate_ros_environment(int(os.environ['COOP_TEST_DOMAIN_ID'])
                        if 'COOP_TEST_DOMAIN_ID' in os.environ else None)
