"""One domain error per package: every exception class a rover_hw module defines derives from
HardwareError (`rover_hw.errors`), so a caller catches one class; a new unrelated error class
fails here. HardwareError is a ValueError, so each keeps the ValueError its callers catch."""
import importlib
import inspect
import pkgutil

import rover_hw
from rover_hw.errors import HardwareError

#: the error classes known today and the builtin base their callers catch
KNOWN = {
    'rover_hw.protocol.ProtocolError': ValueError,
    'rover_hw.safety.CommandRefused': ValueError,
}


def error_classes() -> dict[str, type]:
    """Every exception class (warnings aside) defined in a module of the package, by name."""
    out = {}
    for info in pkgutil.walk_packages(rover_hw.__path__, 'rover_hw.'):
        module = importlib.import_module(info.name)
        for cls in vars(module).values():
            if (inspect.isclass(cls) and issubclass(cls, BaseException)
                    and not issubclass(cls, Warning) and cls.__module__ == module.__name__):
                out[f'{module.__name__}.{cls.__qualname__}'] = cls
    return out


def test_every_error_derives_from_the_root():
    found = error_classes()
    assert set(KNOWN) <= set(found)
    assert [name for name, cls in found.items() if not issubclass(cls, HardwareError)] == []


def test_known_errors_keep_their_builtin_base():
    found = error_classes()
    assert [name for name, base in KNOWN.items() if not issubclass(found[name], base)] == []
