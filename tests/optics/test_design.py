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


def test_corrector_length_counts_the_defocus_and_lens_edges_must_not_cross():
    """The stack ends back_focus_mm before the detector, which sits defocus_mm beyond the bare focus: a
    stack that fits with the detector moved out reaches into the diagonal when it is moved back. Lenses
    must keep a positive thickness at their rims and fit their spheres."""
    data = load_design("art").model_dump()
    stack = sum(s["thickness_mm"] for s in data["corrector"]["surfaces"][:-1]) + data["corrector"]["back_focus_mm"]
    d, b = data["secondary"]["distance_to_focus_mm"], data["secondary"]["minor_axis_mm"] / 2
    data["focal_plane"]["defocus_mm"] = stack - d + b - 1.0         # first surface 1 mm inside the diagonal
    with pytest.raises(ValueError, match="reach past the diagonal"):
        Design.model_validate(data)
    data["focal_plane"]["defocus_mm"] = stack - d + b + 1.0
    Design.model_validate(data)
    # a biconvex lens too thin for its diameter: sag(R = 100 mm, h = 40 mm) = 8.35 mm on either side
    data = load_design("bare").model_dump()
    lens = [{"radius_mm": 100.0, "thickness_mm": 12.0, "material": "N-BK7", "semi_diameter_mm": 40.0},
            {"radius_mm": -100.0, "thickness_mm": 0.0, "material": "air", "semi_diameter_mm": 40.0}]
    data["corrector"] = {"enabled": True, "back_focus_mm": 40.0, "surfaces": lens}
    with pytest.raises(ValueError, match="corrector.surfaces.0.thickness_mm: the N-BK7 space"):
        Design.model_validate(data)
    lens[0]["thickness_mm"] = 17.0                               # edge 0.3 mm
    Design.model_validate(data)
    lens[0]["semi_diameter_mm"] = 101.0
    with pytest.raises(ValueError, match="semi_diameter_mm"):
        Design.model_validate(data)


def test_housing_must_hold_the_focuser_and_coatings_are_checked():
    with pytest.raises(ValueError, match="housing_mm"):
        Design.model_validate(_with(focal_plane__housing_mm=80.0))
    data = load_design("art").model_dump()
    data["corrector"]["ar_reflectance"] = 1.5
    with pytest.raises(ValueError, match="ar_reflectance"):
        Design.model_validate(data)
    data["corrector"]["ar_reflectance"] = "uncoated"
    assert not Design.model_validate(data).corrector.coated
    assert load_design("art").corrector.coated and load_design("art").corrector.ar_reflectance == 0.005


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
