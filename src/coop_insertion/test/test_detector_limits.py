"""The detector-limit study (coop_insertion.detector_limits) and the bench's other backgrounds
(marker_render.background_scene, SLOT): poses, limits, the table, a tiny run on the sim."""
from __future__ import annotations

import math

import numpy as np
import pytest

from coop_insertion.detector_limits import (
    CellResult,
    camera_pose,
    derive_limits,
    format_table,
    measure,
)
from coop_insertion.errors import InsertionError
from coop_insertion.marker_render import (
    BACKGROUNDS,
    SLOT,
    background_scene,
    random_scene,
    sim_intrinsics,
)
from coop_insertion.markers import EllipseDetector

K = sim_intrinsics(640, 480)


def _match(found, scene):
    hits, used = 0, set()
    for c, r in zip(scene.centres, scene.radius_px, strict=False):
        d = [math.hypot(m.u - c[0], m.v - c[1]) for m in found]
        j = int(np.argmin(d)) if d else -1
        if j >= 0 and d[j] < 0.5 * r and j not in used:
            used.add(j)
            hits += 1
    return hits, len(found) - len(used)


def test_background_scene_renders_discs_in_the_image():
    rng = np.random.default_rng(3)
    for kind in BACKGROUNDS:
        s = background_scene(rng, K, 640, 480, kind)
        assert s.image.shape == (480, 640) and s.image.dtype == np.uint8
        assert 2 <= len(s.centres) <= 5
        assert np.all((s.radius_px > 2.5) & (s.radius_px < 80))
        assert np.all((s.centres > 0) & (s.centres < [640, 480]))
        e = background_scene(rng, K, 640, 480, kind, with_markers=False)
        assert len(e.centres) == 0
    with pytest.raises(InsertionError):
        background_scene(rng, K, 640, 480, 'sand')


def test_default_detector_on_other_backgrounds():
    """White discs 3-70 px on gravel, rock, metal and under a shadow: found, and nothing on
    the same backgrounds without discs (the bench's rates: bench/markers.py)."""
    rng = np.random.default_rng(21)
    det = EllipseDetector(K=K)
    hits = total = spurious = false = 0
    for kind in BACKGROUNDS:
        for _ in range(2):
            s = background_scene(rng, K, 640, 480, kind)
            h, x = _match(det.detect(s.image), s)
            hits, total, spurious = hits + h, total + len(s.centres), spurious + x
        false += len(det.detect(background_scene(rng, K, 640, 480, kind,
                                                 with_markers=False).image))
    assert hits >= 0.9 * total, f'{hits} of {total}'
    assert spurious == 0 and false == 0


def test_default_detector_finds_slot_sized_markers():
    """The slot's 0.25 in markers at 0.65-0.95 m: 2.8-4.2 px radius."""
    rng = np.random.default_rng(8)
    det = EllipseDetector(K=K)
    hits = total = 0
    for _ in range(5):
        s = random_scene(rng, K, 640, 480, plate=SLOT, distance_m=(0.65, 0.95),
                         occlude_probability=0.0)
        assert np.all(s.radius_px < 4.5)
        h, x = _match(det.detect(s.image), s)
        hits, total = hits + h, total + len(s.centres)
        assert x == 0
    assert hits >= 0.8 * total, f'{hits} of {total}'


def test_camera_pose_range_and_incidence():
    rng = np.random.default_rng(0)
    marker, normal = np.array([3.0, 0.1, 0.37]), np.array([0.0, 1.0, 0.0])
    for inc in (0.0, 30.0, 75.0):
        eye, R = camera_pose(marker, normal, 0.9, math.radians(inc), rng=rng, fx=851.0,
                             width=640, height=480)
        ray = marker - eye
        assert np.linalg.norm(ray) == pytest.approx(0.9)
        assert math.degrees(math.acos(-ray @ normal / 0.9)) == pytest.approx(inc, abs=1e-6)
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)
        p = R.T @ ray
        u, v = 851.0 * p[:2] / p[2]
        assert p[2] > 0 and abs(u) <= 0.3 * 320 + 1e-6 and abs(v) <= 0.3 * 240 + 1e-6


def test_derive_limits_and_table():
    def cell(d, i, k):
        return CellResult(d, i, 20, k, 0, 0.1)
    # detected from 5 px on up to 45 deg, 6 px at 60 deg, never at 75 deg; a dip at 4 px
    cells = []
    for d in (3.0, 4.0, 5.0, 6.0, 8.0):
        for i in (0.0, 30.0, 45.0, 60.0, 75.0):
            ok = (d >= 5 and i <= 45) or (d >= 6 and i == 60)
            cells.append(cell(d, i, 20 if ok else (20 if (d, i) == (3.0, 0.0) else 12)))
    lim = derive_limits(cells, rate=0.97)
    assert lim['min_diameter_px'] == 5.0        # 3 px passes, 4 px does not: from 5 on
    assert lim['max_incidence_deg'] == 60.0     # 6 px and larger still pass at 60 deg
    assert lim['min_diameter_px_by_incidence'] == {'0': 5.0, '30': 5.0, '45': 5.0,
                                                   '60': 6.0, '75': None}
    result = {'settings': {'width': 640, 'height': 480, 'fx': 851.0, 'per_cell': 20,
                           'slot_marker_diameter_m': 0.00635},
              'cells': [c.__dict__ for c in cells], 'limits': lim}
    text = format_table(result)
    assert 'min_diameter_px 5 px, max_incidence_deg 60 deg' in text
    assert len(text.splitlines()) == 2 + 5 + 2


def test_measure_on_the_sims_renders():
    """One cell through rover_sim's own renderer: 0.25 in markers 12 px across, straight on."""
    pytest.importorskip('pybullet')
    cells, settings = measure(diameters_px=(12.0,), incidences_deg=(0.0,), per_cell=2, seed=1)
    assert len(cells) == 1 and cells[0].renders == 2
    assert cells[0].detected == 2 and cells[0].false_markers == 0
    assert settings['fx'] == pytest.approx(851.3, abs=0.1)
    with pytest.raises(InsertionError):
        measure(incidences_deg=(95.0,), per_cell=1)


def test_the_masters_placement_limits_are_within_the_measured_ones():
    # task_view admits the master's camera poses by marker_min_diameter_px and
    # marker_max_incidence_deg: both must lie inside what the study measured for the detector
    # the master runs (its defaults are the detector's own)
    import json
    from pathlib import Path

    from coop_insertion import markers
    from coop_insertion.master_node import PARAMS
    data = json.loads((Path(__file__).resolve().parents[3] / 'docs' / 'results' / 'data' /
                       'detector_limits.json').read_text())
    lim = data['limits']
    inc = PARAMS['marker_max_incidence_deg'].default
    assert inc <= lim['max_incidence_deg']
    need = [d for a, d in lim['min_diameter_px_by_incidence'].items() if float(a) <= inc + 1e-9]
    assert None not in need and PARAMS['marker_min_diameter_px'].default >= max(need)
    assert (PARAMS['marker_min_contrast'].default, PARAMS['marker_min_coverage'].default,
            PARAMS['marker_max_residual_px'].default) == (
        markers.DEFAULT_MIN_CONTRAST, markers.DEFAULT_MIN_COVERAGE,
        markers.DEFAULT_MAX_RESIDUAL_PX)
