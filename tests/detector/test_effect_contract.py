"""The contract every registered effect keeps, checked over the whole registry (built-in and plugins):
zero strength is the identity, ``describe()`` states units and bounds, and the same seeds give the same
bytes on one and two worker threads. A new effect joins these checks by declaring ``identity``."""

import numpy as np
import pytest
from helpers import small_sensor

from detector import Detector, build_effects, registry

NAMES = sorted(registry())
def _numeric(schema: dict) -> bool:
    if "enum" in schema or "const" in schema:  # a choice among values, not a quantity
        return False
    kinds = {schema.get("type")} | {a.get("type") for a in schema.get("anyOf", [])}
    return bool(kinds & {"number", "integer"}) and not kinds & {"array", "object", "string"}


@pytest.mark.parametrize("name", NAMES)
def test_effect_declares_its_identity(name):
    cls = registry()[name]
    assert cls.identity is not None or cls.no_identity, f"{name}: declare identity (zero strength) or no_identity"


@pytest.mark.parametrize("name", [n for n in NAMES if registry()[n].identity is not None])
def test_zero_strength_is_the_identity(name):
    s = small_sensor(width=200, height=160)
    ref = Detector(s).expose(200.0, 10.0, frame_seed=5)
    out = Detector(s, build_effects({name: registry()[name].identity}, s)).expose(200.0, 10.0, frame_seed=5)
    assert out.tobytes() == ref.tobytes()


@pytest.mark.parametrize("name", NAMES)
def test_describe_has_a_doc_units_and_bounds(name):
    d = registry()[name].describe()
    assert len(d["doc"]) > 40, name
    props = d["params"].get("properties", {})
    for key, schema in props.items():
        if not _numeric(schema):
            continue
        desc = schema.get("description", "")
        assert "unit" in schema or ("[" in desc and "]" in desc), f"{name}.{key}: no unit ({desc!r})"
        bounded = any(b in schema or any(b in a for a in schema.get("anyOf", []))
                      for b in ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum"))
        assert bounded, f"{name}.{key}: no bound"


def test_every_numeric_parameter_has_a_machine_readable_unit():
    """``newtsim effects NAME`` (describe()): every numeric parameter, arrays of numbers included, has a "unit"
    key (the one the field declares, else its description's bracketed unit, else its name's suffix)."""
    for name in NAMES:
        for key, schema in registry()[name].describe()["params"].get("properties", {}).items():
            kinds = [schema] + schema.get("anyOf", [])
            numeric = any(k.get("type") in ("number", "integer") or
                          k.get("items", {}).get("type") in ("number", "integer") for k in kinds)
            if not numeric:
                continue
            unit = schema.get("unit")
            assert isinstance(unit, str) and unit, f"{name}.{key}: no unit key"
            # a unit the field does not declare is read from its description's last bracket
            desc = (schema.get("description") or "").rstrip()
            if desc.endswith("]") and "," not in desc[desc.rindex("["):] and "unit" not in _declared(name, key):
                assert unit == desc[desc.rindex("[") + 1:-1].strip(), f"{name}.{key}: {unit!r} vs {desc!r}"


def _declared(name: str, key: str) -> dict:
    extra = registry()[name].Params.model_fields[key].json_schema_extra
    return extra if isinstance(extra, dict) else {}


@pytest.mark.parametrize("name", [n for n in NAMES if registry()[n].identity is not None])
def test_same_bytes_on_one_and_two_workers(name):
    s = small_sensor(width=240, height=520)  # more than two row bands
    effects1 = build_effects({name: {}}, s)  # the defaults: a setting that does something
    signal = np.linspace(50.0, 5000.0, s.height * s.width, dtype=np.float32).reshape(s.height, s.width)
    one = Detector(s, effects1, workers=1).expose(signal, 10.0, frame_seed=11)
    two = Detector(s, effects1, workers=2).expose(signal, 10.0, frame_seed=11)
    assert one.tobytes() == two.tobytes()
