"""One domain error per package: every exception class a package's modules define derives from
that package's one root error, so a caller catches one class; a new error class outside it fails
here. Each keeps the builtin base its callers already catch (KNOWN)."""
from __future__ import annotations

import importlib
import inspect
import pkgutil

import pytest

#: package -> its root error (module, class)
ROOTS = {
    'rover_sim': ('rover_sim.errors', 'SimError'),
    'coop_id': ('coop_id.errors', 'CoopIdError'),
    'coop_mapping': ('coop_mapping.errors', 'MappingError'),
    'coop_viewplan': ('coop_viewplan.errors', 'ViewplanError'),
    'coop_common': ('coop_common.errors', 'CoopCommonError'),
    'coop_insertion': ('coop_insertion.errors', 'InsertionError'),
    'coop_bringup': ('coop_bringup.report', 'MissionError'),
    'rover_hw': ('rover_hw.errors', 'HardwareError'),
    'rover_bag': ('rover_bag.errors', 'BagError'),
    'coop_braid': ('coop_braid.errors', 'BraidError'),
}
#: error classes and the builtin base their callers catch
KNOWN = {
    'rover_sim.config.ConfigError': ValueError,
    'rover_sim.trajectory.TrajectoryError': ValueError,
    'coop_id.model.ModelError': ValueError,
    'coop_id.consistency.ConsistencyError': ValueError,
    'coop_id.identifier_core.IdentifierError': ValueError,
    'coop_id.excitation.ExcitationError': ValueError,
    'coop_id.estimators.EstimationError': ValueError,
    'coop_id.estimators.RankDeficientError': ValueError,
    'coop_id.information.InformationError': ValueError,
    'coop_id.offline.BagError': ValueError,
    'coop_mapping.errors.OptionError': ValueError,
    'coop_mapping.ros_conv.CloudFormatError': ValueError,
    'coop_mapping.gauss.NotPositiveDefinite': ValueError,
    'coop_mapping.target_frame.TargetFrameError': ValueError,
    'coop_mapping.fig_3_24.ConfigError': ValueError,
    'coop_mapping.stereo.StereoError': ValueError,
    'coop_mapping.motion.MotionError': ValueError,
    'coop_mapping.voxelmap.MapInputError': ValueError,
    'coop_mapping.voxelmap.ScanRejected': ValueError,
    'coop_mapping.voxelmap.MapFileError': RuntimeError,
    'coop_viewplan.errors.OptionError': ValueError,
    'coop_viewplan.nbv.PlanningError': RuntimeError,
    'coop_viewplan.grid.MapError': ValueError,
    'coop_viewplan.grid.EmptyMapError': ValueError,
    'coop_viewplan.placement.PlacementError': ValueError,
    'coop_common.rover_geometry.ReachError': ValueError,
    'coop_common.dynparams.TruthFileError': ValueError,
    'coop_bringup.rig.SimStalled': RuntimeError,
    'rover_hw.protocol.ProtocolError': ValueError,
    'rover_hw.safety.CommandRefused': ValueError,
    'rover_bag.bagio.BagNotFoundError': FileNotFoundError,
    'rover_bag.bagio.UnknownTypeError': KeyError,
    'rover_bag.playback.RemapError': ValueError,
    'coop_braid.stage.StageSolveError': ValueError,
    'coop_braid.carrier.CarrierError': ValueError,
}


def error_classes(package: str) -> dict[str, type]:
    """Every exception class (warnings aside) defined in a module of `package`, by name."""
    pkg = importlib.import_module(package)
    out = {}
    for info in pkgutil.walk_packages(pkg.__path__, f'{package}.'):
        module = importlib.import_module(info.name)
        for cls in vars(module).values():
            if (inspect.isclass(cls) and issubclass(cls, BaseException)
                    and not issubclass(cls, Warning) and cls.__module__ == module.__name__):
                out[f'{module.__name__}.{cls.__qualname__}'] = cls
    return out


@pytest.mark.parametrize('package', sorted(ROOTS))
def test_every_error_of_a_package_derives_from_its_root(package):
    module, name = ROOTS[package]
    root = getattr(importlib.import_module(module), name)
    found = error_classes(package)
    known = {k: base for k, base in KNOWN.items() if k.startswith(f'{package}.')}
    assert set(known) <= set(found), set(known) - set(found)
    assert [n for n, cls in found.items() if not issubclass(cls, root)] == []
    assert [n for n, base in known.items() if not issubclass(found[n], base)] == []
