"""The equinox "abstract or final" pattern, checked over every eqsmooth Module.

equinox 0.13 no longer enforces it, so this test does: a Module class defined
in eqsmooth is either abstract (its name starts with ``Abstract``) or final
(no eqsmooth class subclasses it), and concrete classes override only
abstract methods of their bases.
"""

import importlib
import inspect
import pkgutil

import equinox as eqx


def _eqsmooth_modules():
    import eqsmooth

    yield eqsmooth
    for info in pkgutil.walk_packages(eqsmooth.__path__, prefix="eqsmooth."):
        yield importlib.import_module(info.name)


def _module_classes():
    seen = {}
    for mod in _eqsmooth_modules():
        for _, obj in inspect.getmembers(mod, inspect.isclass):
            if (
                issubclass(obj, eqx.Module)
                and obj.__module__.startswith("eqsmooth")
                and obj.__qualname__ not in seen
            ):
                seen[f"{obj.__module__}.{obj.__qualname__}"] = obj
    return seen


def test_found_classes():
    classes = _module_classes()
    assert len(classes) > 10, sorted(classes)


def test_abstract_or_final():
    classes = _module_classes()
    bad = []
    for name, cls in classes.items():
        if cls.__name__.startswith("Abstract"):
            continue
        for other_name, other in classes.items():
            if other is not cls and cls in other.__mro__[1:]:
                bad.append(f"{other_name} subclasses concrete {name}")
    assert not bad, "\n".join(bad)


def test_abstract_classes_are_named_abstract():
    bad = [
        name
        for name, cls in _module_classes().items()
        if inspect.isabstract(cls) and not cls.__name__.startswith("Abstract")
    ]
    assert not bad, bad


def test_only_abstract_methods_are_overridden():
    bad = []
    for name, cls in _module_classes().items():
        for base in cls.__mro__[1:]:
            if not (
                issubclass(base, eqx.Module) and base.__module__.startswith("eqsmooth")
            ):
                continue
            for attr, value in vars(cls).items():
                if attr.startswith("__") or attr not in vars(base):
                    continue
                inherited = vars(base)[attr]
                if callable(inherited) and not getattr(
                    inherited, "__isabstractmethod__", False
                ):
                    bad.append(f"{name}.{attr} overrides concrete {base.__name__}")
    assert not bad, "\n".join(bad)
