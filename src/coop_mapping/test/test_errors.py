"""One domain error per package: every exception class a coop_mapping module defines derives from
MappingError (`coop_mapping.errors`), so a caller catches one class; a new unrelated error class
fails here. It derives from Exception: the package mixes ValueError and RuntimeError errors and
each keeps its builtin base, checked below."""
import importlib
import inspect
import pkgutil

import coop_mapping
from coop_mapping.errors import MappingError

#: the error classes known today and the builtin base their callers catch
KNOWN = {
    'coop_mapping.ros_conv.CloudFormatError': ValueError,
    'coop_mapping.gauss.NotPositiveDefinite': ValueError,
    'coop_mapping.target_frame.TargetFrameError': ValueError,
    'coop_mapping.fig_3_24.ConfigError': ValueError,
    'coop_mapping.stereo.StereoError': ValueError,
    'coop_mapping.motion.MotionError': ValueError,
    'coop_mapping.voxelmap.MapInputError': ValueError,
    'coop_mapping.voxelmap.ScanRejected': ValueError,
    'coop_mapping.voxelmap.MapFileError': RuntimeError,
}


def error_classes() -> dict[str, type]:
    """Every exception class (warnings aside) defined in a module of the package, by name."""
    out = {}
    for info in pkgutil.walk_packages(coop_mapping.__path__, 'coop_mapping.'):
        module = importlib.import_module(info.name)
        for cls in vars(module).values():
            if (inspect.isclass(cls) and issubclass(cls, BaseException)
                    and not issubclass(cls, Warning) and cls.__module__ == module.__name__):
                out[f'{module.__name__}.{cls.__qualname__}'] = cls
    return out


def test_every_error_derives_from_the_root():
    found = error_classes()
    assert set(KNOWN) <= set(found)
    assert [name for name, cls in found.items() if not issubclass(cls, MappingError)] == []


def test_known_errors_keep_their_builtin_base():
    found = error_classes()
    assert [name for name, base in KNOWN.items() if not issubclass(found[name], base)] == []
