"""Every test run gets its own ROS domain and single-threaded BLAS before rclpy is imported,
and Ctrl-C as a terminal has it. `make test` runs the tests on two pytest-xdist workers, each
on its own domain, whole files to a worker, the longest graph files handed out first."""
import os
import signal
from pathlib import Path

import pytest

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('OMP_NUM_THREADS', '1')
os.environ.setdefault('MPLBACKEND', 'Agg')

from coop_common.testing import free_domain_id, isolate_ros_environment


def _domain_id() -> int | None:
    """COOP_TEST_DOMAIN_ID, or for an xdist worker (gw0, gw1, ...) one of the run's own: from
    its controller's pid on, the worker's number picks one of the domains no other run on the
    machine uses (free_domain_id; None: isolate_ros_environment's pick from this pid)."""
    if 'COOP_TEST_DOMAIN_ID' in os.environ:
        return int(os.environ['COOP_TEST_DOMAIN_ID'])
    worker = os.environ.get('PYTEST_XDIST_WORKER', '')
    if worker.startswith('gw') and worker[2:].isdigit():
        n = int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1'))
        return free_domain_id(os.getppid() * n, nth=int(worker[2:]))
    return None


isolate_ros_environment(_domain_id())

# A run started in the background of a non-interactive shell (a CI runner, `cmd &`) inherits
# SIGINT ignored, and every process it starts inherits that: `ros2 launch` would then ignore
# the Ctrl-C a test sends it, and never escalate to SIGTERM / SIGKILL for a node that hangs.
# Tests send Ctrl-C as a terminal does, to processes that handle it as a terminal's would.
signal.signal(signal.SIGINT, signal.default_int_handler)


#: the graph tests that take longest, started first so that no worker ends the run alone
#: with one of them (the rest by collection order)
FIRST = ('test/test_mission_graph.py', 'test/test_lockstep_graph.py',
         'test/test_hw_identification_graph.py', 'test/test_bag_replay.py',
         'test/test_sim_graph.py')


def pytest_collection_modifyitems(session, config, items) -> None:
    def rank(item) -> int:
        path = item.nodeid.split('::')[0]
        return FIRST.index(path) if path in FIRST else len(FIRST)
    items.sort(key=rank)      # stable: within a rank, collection order


# --- Figures a test measures, for the results pages (coop_common.figures) ---------------------

def pytest_addoption(parser) -> None:
    parser.addoption('--figures-json', metavar='PATH', default=None,
                     help='write the figures the tests record (the `figures` fixture) to PATH '
                          'as JSON, for a results page')


def pytest_configure(config) -> None:
    from coop_common.figures import FigureLog
    path = config.getoption('--figures-json')
    if path and (config.getoption('numprocesses', None) or os.environ.get('PYTEST_XDIST_WORKER')):
        raise pytest.UsageError('--figures-json: run without -n (one process keeps the records)')
    config.coop_figures = FigureLog()


def pytest_sessionfinish(session, exitstatus) -> None:
    path = session.config.getoption('--figures-json')
    if path:
        session.config.coop_figures.write(Path(path))


@pytest.fixture
def figures(request):
    """The session's FigureLog: `figures.add(KEY, {...})` keeps a test's measured figures."""
    return request.config.coop_figures
