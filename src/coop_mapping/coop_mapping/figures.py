"""What test_initialisation.py measures, as it prints it and as docs/results/mapping.md shows
it (coop_common.figures: the test records, `pytest --figures-json PATH` writes the file the
page's block is made from). Key: `initialisation`."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from coop_common.figures import records


def _v(x: Sequence[float], digits: int) -> str:
    return '[' + ' '.join(f'{v:.{digits}f}' for v in x) + ']'


def initialisation_lines(r: Mapping[str, Any]) -> str:
    """One `initialisation` record: the target fix's position sigma at both ranges, each
    frame's error in the common frame against its predicted sigma, and the last cloud."""
    lines = [f'target fix position sigma at 1.6 m {_v(r["far_sigma_m"], 3)} m (largest '
             f'{max(r["far_sigma_m"]):.3f} > {r["threshold_m"]:g}: waits), at 1.0 m '
             f'{_v(r["fix_sigma_m"], 3)} m']
    for f in r['frames']:
        lines.append(
            f'frame {f["frame"]}: dead-reckoned position error {f["dead_reckoned_m"]:.3f} m; '
            f'common-frame position error {_v(f["position_error_m"], 4)} m, rotation error '
            f'{_v(f["rotation_error_deg"], 2)} deg, predicted sigma {_v(f["sigma_m"], 4)} m / '
            f'{_v(f["sigma_deg"], 2)} deg')
    lines.append(f'frame {r["frames"][-1]["frame"]} cloud: {r["cloud_points"]} points, median '
                 f'distance to the true-pose cloud {r["cloud_median_m"]:.3f} m')
    return '\n'.join(lines)


def format_initialisation(data: Mapping[str, Any]) -> str:
    """The `initialisation` records of a figures file."""
    return '\n'.join(initialisation_lines(r) for r in records(data, 'initialisation'))
