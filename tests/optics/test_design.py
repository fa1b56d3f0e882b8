"""Design files: inconsistent designs name the field; the LLVM finder refuses what would abort."""

import pytest

from optics import OpticsError, load_design
from optics.design import Design
from optics.llvm import find_llvm, llvm_major


def _with(**changes):
    data = load_design("bare").model_dump(exclude_none=True)
    for dotted, value in changes.items():
        table, key = dotted.split("__")
        data[table][key] = value
    return data


@pytest.mark.parametrize("change, field", [
    ({"secondary__minor_axis_mm": 500.0}, "secondary.minor_axis_mm"),
    ({"secondary__distance_to_focus_mm": 200.0}, "focus inside the tube wall"),
    ({"baffle__vane_inner_diameter_mm": 300.0}, "closes the aperture"),
    ({"primary__diameter_mm": -4.0}, "primary.diameter_mm"),
    ({"tube__length_mm": 600.0}, "tube.length_mm"),
])
def test_inconsistent_designs_name_the_field(tmp_path, change, field):
    import tomli_w

    path = tmp_path / "bad.toml"
    path.write_text(tomli_w.dumps(_with(**change)))
    with pytest.raises(OpticsError) as exc:
        load_design(str(path))
    assert str(path) in str(exc.value)
    assert field.split(".")[0] in str(exc.value)


def test_unknown_glass_and_overlong_corrector_are_refused():
    data = load_design("bare").model_dump()
    data["corrector"] = {"enabled": True, "surfaces": [{"radius_mm": 100, "thickness_mm": 5, "material": "UNOBTAINIUM"}]}
    with pytest.raises(ValueError, match="unknown glass"):
        Design.model_validate(data)
    data["corrector"] = {"enabled": True, "back_focus_mm": 400.0, "surfaces": [{"thickness_mm": 5}]}
    with pytest.raises(ValueError, match="reach past the diagonal"):
        Design.model_validate(data)


def test_missing_design_lists_the_builtins():
    with pytest.raises(OpticsError, match="art"):
        load_design("no_such_design")


def test_llvm_version_is_read_from_library_names():
    assert llvm_major("/usr/lib/x86_64-linux-gnu/libLLVM-19.so") == 19
    assert llvm_major("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1") == 19
    assert llvm_major("/usr/lib/llvm-15/lib/libLLVM.so") == 15
    assert llvm_major("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1") == 15


def test_pinned_old_llvm_is_refused_with_install_advice(monkeypatch, tmp_path):
    lib = tmp_path / "libLLVM-15.so"
    lib.write_bytes(b"")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(lib))
    with pytest.raises(OpticsError, match="libllvm19"):
        find_llvm()
