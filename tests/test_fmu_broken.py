"""Broken FMUs made by the test from our own builds (FMI 3.0 and 2.0): every
missing variable at once, archives that are not zips, fail a CRC or hold a
corrupt deflate stream, a missing binary for this platform. Each is a clear
error naming the .fmu path, ``minetwin fmus validate`` exits 2 with one line
and no traceback, and no extracted folder is left behind."""

from __future__ import annotations

import tempfile
import zipfile
from pathlib import Path

import fmpy
import pytest

from cosim.errors import ValidationError
from cosim.fmu import (CRUSHER_INTERFACE, MILL_INTERFACE, FmuCallError, FmuComponent,
                       FmuInterfaceError, fmu_path)


@pytest.fixture(scope="module", autouse=True)
def built_fmus():
    from fmus.build import build_all

    build_all()


@pytest.fixture
def no_leftover_folders(tmp_path_factory, monkeypatch):
    """Fails the test if an extracted FMU folder stays in the temporary directory.
    The test gets a temporary directory of its own: in the shared one, another
    process's FMU (a second test run on the machine) may be extracted meanwhile."""
    private = tmp_path_factory.mktemp("tempdir")
    monkeypatch.setattr(tempfile, "tempdir", str(private))
    yield
    assert list(private.glob("minetwin-fmu-*")) == []


def platform(fmi):
    return fmpy.platform_tuple if fmi == 3 else fmpy.platform


def _member_data_offset(path: Path, name: str) -> int:
    """Offset of member ``name``'s (compressed) data in the archive file."""
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo(name)
    raw = path.read_bytes()
    header = info.header_offset
    name_length = int.from_bytes(raw[header + 26:header + 28], "little")
    extra_length = int.from_bytes(raw[header + 28:header + 30], "little")
    return header + 30 + name_length + extra_length


def _copy(source: Path, target: Path, *, stored=(), drop=(), add=()) -> Path:
    with zipfile.ZipFile(source) as src, zipfile.ZipFile(target, "w") as dst:
        for item in src.infolist():
            if any(item.filename.startswith(prefix) for prefix in drop):
                continue
            method = zipfile.ZIP_STORED if item.filename in stored else zipfile.ZIP_DEFLATED
            dst.writestr(item.filename, src.read(item), compress_type=method)
        for name, data in add:
            dst.writestr(name, data)
    return target


def binary_member(fmi):
    suffix = ".so"
    return f"binaries/{platform(fmi)}/crusher{suffix}"


def bad_crc(tmp_path, fmi) -> Path:
    """The binary stored uncompressed with one byte flipped: only the CRC check sees it."""
    path = _copy(fmu_path("crusher", fmi), tmp_path / f"bad_crc_{fmi}.fmu",
                 stored=(binary_member(fmi),))
    raw = bytearray(path.read_bytes())
    raw[_member_data_offset(path, binary_member(fmi)) + 200] ^= 0xFF
    path.write_bytes(bytes(raw))
    return path


def corrupt_deflate(tmp_path, fmi) -> Path:
    """The binary's deflate stream starting with a reserved block type (invalid)."""
    path = _copy(fmu_path("crusher", fmi), tmp_path / f"bad_deflate_{fmi}.fmu")
    raw = bytearray(path.read_bytes())
    start = _member_data_offset(path, binary_member(fmi))
    raw[start:start + 8] = b"\xff" * 8
    path.write_bytes(bytes(raw))
    return path


def not_a_zip(tmp_path, fmi) -> Path:
    path = tmp_path / f"not_a_zip_{fmi}.fmu"
    path.write_bytes(b"this is not an FMU\n" * 100)
    return path


def without_binary(tmp_path, fmi) -> Path:
    other = "darwin64" if fmi == 2 else "aarch64-darwin"
    return _copy(fmu_path("crusher", fmi), tmp_path / f"no_binary_{fmi}.fmu",
                 drop=("binaries/",), add=((f"binaries/{other}/crusher.dylib", b"\0" * 16),))


BROKEN = {
    "bad_crc": (bad_crc, r"must be an intact FMU archive \(.*: member binaries/.*/crusher.so "
                         r"fails its CRC check\)"),
    "corrupt_deflate": (corrupt_deflate, r"must be an intact FMU archive \(.*: member "
                                         r"binaries/.*/crusher.so: corrupt deflate stream"),
    "not_a_zip": (not_a_zip, r"must be an FMU \(a zip archive\).*File is not a zip file"),
    "without_binary": (without_binary, r"must be an FMU with a binary for this platform"),
}


@pytest.mark.parametrize("fmi", [3, 2])
@pytest.mark.parametrize("case", sorted(BROKEN))
def test_broken_archive_is_a_clear_error_naming_the_file(case, fmi, tmp_path,
                                                         no_leftover_folders):
    make, pattern = BROKEN[case]
    path = make(tmp_path, fmi)
    with pytest.raises(ValidationError, match=pattern) as info:
        FmuComponent(path, interface=CRUSHER_INTERFACE)
    message = str(info.value)
    assert str(path) in message and "\n" not in message
    if case == "without_binary":
        needed = platform(fmi)
        other = "darwin64" if fmi == 2 else "aarch64-darwin"
        assert f"lacks binaries/{needed}/crusher.so" in message
        assert f"it has binaries for ['{other}']" in message
        assert "fmpy compile" in message  # our FMUs ship their C sources


@pytest.mark.parametrize("fmi", [3, 2])
@pytest.mark.parametrize("case", sorted(BROKEN))
def test_cli_validate_exits_2_with_one_line(case, fmi, tmp_path, capsys, no_leftover_folders):
    from minetwin.cli import main

    path = BROKEN[case][0](tmp_path, fmi)
    assert main(["fmus", "validate", str(path)]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in captured.err
    assert lines[0].startswith("minetwin fmus validate: error: fmu: must be")
    assert str(path) in lines[0]
    assert main(["fmus", "info", str(path)]) == (0 if case == "without_binary" else 2)


@pytest.mark.parametrize("fmi", [3, 2])
def test_every_missing_variable_is_listed_at_once(fmi, no_leftover_folders):
    with pytest.raises(FmuInterfaceError) as info:
        FmuComponent(fmu_path("crusher", fmi), interface=MILL_INTERFACE)
    problems = info.value.problems
    names = [name for name, _, _ in problems]
    assert names == ["speed_setpoint", "charge_mass", "breakage_rate", "daughter_fraction",
                     "escape_rate", "speed", "torque_drive", "torque_acceleration",
                     "torque_active", "d50"]
    message = str(info.value)
    assert message.startswith(f"{fmu_path('crusher', fmi).name}: 10 variables do not match "
                              "the interface: variable 'speed_setpoint': must be an input")
    assert "variable 'speed': must be an output Float64 variable, a scalar (its causality is " \
           "'input')" in message
    for name in names:
        assert f"variable {name!r}" in message


def test_failure_after_extraction_leaves_no_folder(tmp_path, no_leftover_folders):
    """Instantiation refused (a stale token) and a refused parameter: the folder goes."""
    source = fmu_path("crusher")
    stale = tmp_path / "stale.fmu"
    with zipfile.ZipFile(source) as src, zipfile.ZipFile(stale, "w") as dst:
        for item in src.infolist():
            data = src.read(item)
            if item.filename == "modelDescription.xml":
                data = data.replace(b'instantiationToken="{', b'instantiationToken="{0')
            dst.writestr(item, data)
    with pytest.raises(FmuCallError, match="stale.fmu: instantiate failed"):
        FmuComponent(stale)
    with pytest.raises(FmuCallError, match="exitInitializationMode failed"):
        FmuComponent(source, parameters={"gap_width": -1.0})
    with pytest.raises(ValidationError, match="parameter 'gap'"):
        FmuComponent(source, parameters={"gap": 1.0})


def test_clock_variables_are_named_in_a_warning(tmp_path):
    """FMI 3 Clocks are not exchanged: an FMU with one loads, and a warning says so."""
    from fmus.typed import typed_fmu_file

    clocked = tmp_path / "clocked.fmu"
    with zipfile.ZipFile(typed_fmu_file("counter", 3)) as src, \
            zipfile.ZipFile(clocked, "w") as dst:
        for item in src.infolist():
            data = src.read(item)
            if item.filename == "modelDescription.xml":
                data = data.replace(b"  </ModelVariables>",
                                    b'    <Clock name="tick" valueReference="99" '
                                    b'causality="input" variability="discrete"/>\n'
                                    b"  </ModelVariables>")
            dst.writestr(item, data)
    with pytest.warns(UserWarning, match=r"clocked.fmu: Clock variables are not exchanged by "
                                         r"the master: \['tick'\]"):
        fmu = FmuComponent(clocked)
    fmu.step(0.0, 1.0)
    assert fmu.outputs()["counter"] == 1
    fmu.finish()
