"""One domain error per package: every exception class a rover_bag module defines derives from
BagError (`rover_bag.errors`), so a caller catches one class; a new unrelated error class fails
here. Warnings (DamagedBagWarning) are not errors and are left out."""
import importlib
import inspect
import pkgutil

import rover_bag
from rover_bag.errors import BagError

#: the error classes known today and the builtin base their callers catch
KNOWN = {
    'rover_bag.bagio.BagNotFoundError': FileNotFoundError,
    'rover_bag.bagio.UnknownTypeError': KeyError,
    'rover_bag.bagio.DamagedBagError': Exception,
    'rover_bag.playback.RemapError': ValueError,
}


def error_classes() -> dict[str, type]:
    """Every exception class (warnings aside) defined in a module of the package, by name."""
    out = {}
    for info in pkgutil.walk_packages(rover_bag.__path__, 'rover_bag.'):
        module = importlib.import_module(info.name)
        for cls in vars(module).values():
            if (inspect.isclass(cls) and issubclass(cls, BaseException)
                    and not issubclass(cls, Warning) and cls.__module__ == module.__name__):
                out[f'{module.__name__}.{cls.__qualname__}'] = cls
    return out


def test_every_error_derives_from_the_root():
    found = error_classes()
    assert set(KNOWN) <= set(found)
    assert [name for name, cls in found.items() if not issubclass(cls, BagError)] == []


def test_known_errors_keep_their_builtin_base():
    found = error_classes()
    assert [name for name, base in KNOWN.items() if not issubclass(found[name], base)] == []
