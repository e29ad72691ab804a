"""One domain error per package: every exception class a coop_id module defines derives from
CoopIdError (`coop_id.errors`), so a caller catches one class; a new unrelated error class fails
here. CoopIdError is a ValueError, so each keeps the ValueError its callers catch."""
import importlib
import inspect
import pkgutil

import coop_id
from coop_id.errors import CoopIdError

#: the error classes known today and the builtin base their callers catch
KNOWN = {
    'coop_id.model.ModelError': ValueError,
    'coop_id.consistency.ConsistencyError': ValueError,
    'coop_id.identifier_core.IdentifierError': ValueError,
    'coop_id.excitation.ExcitationError': ValueError,
    'coop_id.estimators.EstimationError': ValueError,
    'coop_id.estimators.RankDeficientError': ValueError,
    'coop_id.information.InformationError': ValueError,
    'coop_id.offline.BagError': ValueError,
}


def error_classes() -> dict[str, type]:
    """Every exception class (warnings aside) defined in a module of the package, by name."""
    out = {}
    for info in pkgutil.walk_packages(coop_id.__path__, 'coop_id.'):
        module = importlib.import_module(info.name)
        for cls in vars(module).values():
            if (inspect.isclass(cls) and issubclass(cls, BaseException)
                    and not issubclass(cls, Warning) and cls.__module__ == module.__name__):
                out[f'{module.__name__}.{cls.__qualname__}'] = cls
    return out


def test_every_error_derives_from_the_root():
    found = error_classes()
    assert set(KNOWN) <= set(found)
    assert [name for name, cls in found.items() if not issubclass(cls, CoopIdError)] == []


def test_known_errors_keep_their_builtin_base():
    found = error_classes()
    assert [name for name, base in KNOWN.items() if not issubclass(found[name], base)] == []
