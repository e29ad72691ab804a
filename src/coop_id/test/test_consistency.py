"""Physical consistency projection, honest reports, change detection."""
import numpy as np

from coop_common.dynparams import check_physical, load_truth
from coop_id.consistency import ChangeDetector, make_report, project_physical
from coop_id.model import IDX


def test_consistent_vector_unchanged():
    x = load_truth().to_vector()
    np.testing.assert_allclose(project_physical(x), x, atol=1e-12)


def test_projection_repairs_every_violation():
    x = load_truth().to_vector()
    x[IDX['mass']] = -1.0
    x[IDX['Ixx']], x[IDX['Iyy']], x[IDX['Izz']] = 0.01, 0.01, 0.5   # triangle violated
    x[IDX['Ixy']] = 0.2                                              # and indefinite
    x[IDX['k_x']], x[IDX['b_yaw']] = -5.0, -1.0
    assert check_physical(x)
    p = project_physical(x)
    assert check_physical(p) == []
    assert p[IDX['k_x']] == 0 and p[IDX['b_yaw']] == 0 and p[IDX['mass']] > 0
    np.testing.assert_allclose(p[IDX['cg_x']:IDX['cg_z'] + 1], x[IDX['cg_x']:IDX['cg_z'] + 1])


def test_report_flags_unobservable_and_interval_covers():
    x = load_truth().to_vector()
    prior = np.abs(x) + 1.0
    std = 0.01 * prior
    std[IDX['k_z']] = prior[IDX['k_z']]  # data cannot see it
    info = np.full(22, 6.0)
    info[IDX['k_z']] = 0.05
    rep = make_report(x, np.diag(std ** 2), info, prior_std=prior)
    assert not rep.observable[IDX['k_z']] and rep.observable.sum() == 21
    assert rep.consistent
    assert np.all((rep.ci_low <= x) & (x <= rep.ci_high))
    assert np.all(rep.ci_low[IDX['k_x']:] >= 0)


def test_change_detector():
    det = ChangeDetector(threshold=4.0, warmup_windows=2)
    assert not det.check(10.0) and not det.check(10.0)   # warm-up
    assert not det.check(1.2)
    assert det.check(9.0) and det.detections == 1
