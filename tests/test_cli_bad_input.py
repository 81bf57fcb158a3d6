"""Every subcommand refuses bad input with exit code 2 and a message naming the argument.

Run in-process through ``minetwin.cli.main`` (one interpreter for all cases): an
exception that escapes is a traceback a user would see, and fails the case.
"""

import os
import shutil
import zipfile
from pathlib import Path

import pytest

from minetwin.cli import main

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = str(ROOT / "examples" / "step_response.toml")
DESIGN = str(ROOT / "surrogate" / "rom" / "data" / "paper_design")
VALIDATION = str(ROOT / "surrogate" / "rom" / "data" / "paper_validation")


@pytest.fixture(scope="module")
def bad(tmp_path_factory):
    """A folder of bad inputs: a missing path, a folder, text that is not a database, ..."""
    folder = tmp_path_factory.mktemp("bad")
    (folder / "folder").mkdir()
    (folder / "text.md").write_text("# not a database, not a zip, not a checkpoint\n")
    (folder / "empty.sqlite").write_bytes(b"")
    (folder / "latin1.toml").write_bytes(b"\xff\xfe[simulation]\nuntil_s = 3\n")
    (folder / "broken.toml").write_text("[simulation\nuntil_s = 3\n")
    (folder / "not_a_zip.fmu").write_text("not a zip")
    example = Path(SCENARIO).read_text()      # two errors, both reported by one validation
    (folder / "two_errors.toml").write_text(example.replace("grade = 0.2 ", "grade = 1.5 ")
                                            .replace('to = "mill.feed"', 'to = "mill.side"'))
    with zipfile.ZipFile(folder / "no_description.fmu", "w") as archive:
        archive.writestr("readme.txt", "an archive without modelDescription.xml")
    truncated = folder / "truncated.sqlite"
    _events_store(truncated)
    with truncated.open("r+b") as handle:
        handle.truncate(truncated.stat().st_size // 2)
    return folder


def _events_store(path: Path) -> None:
    import numpy as np

    from cosim.events import EventStore

    with EventStore(path) as store:
        batch = {"id": np.arange(3), "mass": np.ones(3), "position": np.zeros((3, 3)),
                 "grade": np.full(3, 0.5), "hardness": np.ones(3),
                 "origin_block": np.zeros(3, int), "f": np.full((3, 16), 1 / 16)}
        for k in range(2000):
            store.record_batch("appear", "source", float(k), batch)


CASES = [
    # (arguments, text the message must contain)
    ("simulate {bad}/missing.toml --out {out}", "scenario: must be an existing TOML file"),
    ("simulate {bad}/folder --out {out}", "is a folder"),
    ("simulate {bad}/latin1.toml --out {out}", "scenario: must be a UTF-8 text file"),
    ("simulate {bad}/broken.toml --out {out}", "scenario: must be valid TOML"),
    ("simulate {scenario} --out /proc/minetwin-nope --until 5 --quiet", "/proc/minetwin-nope"),
    ("simulate {scenario} --out {out} --until 0", "--until: must be > 0 s"),
    ("simulate {scenario} --out {out} --until nan", "--until: must be > 0 s"),
    ("simulate {scenario} --out {out} --storage-model foo", "--storage-model: must be one of"),
    ("simulate {scenario} --out {out} --model-option bogus=1",
     "assets.stockpile.options.bogus"),
    ("simulate {scenario} --out {out} --model-option novalue", "--model-option: must be KEY=VALUE"),
    ("simulate {scenario} --out {out} --rest-port 70000", "--rest-port: must be in [0, 65535]"),
    ("simulate {scenario} --out {out} --unitl 10", "minetwin simulate: error: unrecognized "
                                                   "arguments: --unitl"),
    ("simulate {scenario} --out {out} --seed 1.5", "--seed: invalid int value"),
    ("simulate {scenario} --out {out} --seed -1", "simulation.seed: must be"),
    ("simulate {bad}/two_errors.toml --out {out}",
     "assets.left.grade: must be finite and >= 0 and <= 1 (got 1.5)"),
    ("simulate {bad}/two_errors.toml --out {out}",
     "flows[4].to: must be an inlet of mill (mill): one of ['feed'] (got 'mill.side')"),
    ("events summary {bad}/text.md", "database: must be an events.sqlite"),
    ("events summary {bad}/empty.sqlite", "empty file, not an event store"),
    ("events summary {bad}/truncated.sqlite", "database: must be an events.sqlite"),
    ("events summary {bad}/folder", "database: must be an events.sqlite"),
    ("events history {bad}/missing.sqlite 1", "no such file"),
    ("events export {bad}/text.md --out {out}", "database: must be an events.sqlite"),
    ("reproduce nothing --out {out}", "argument NAME: invalid choice"),
    ("reproduce step-response --out /proc/minetwin-nope --quick --quiet", "/proc/minetwin-nope"),
    ("integration-test --duration -1 --out {out}", "duration: must be in (0, 86400] s"),
    ("integration-test --duration 10 --speed 0 --out {out}", "speed: must be in (0, 1000]"),
    ("integration-test --duration 10 --out {out} --model foo", "model: must be one of"),
    ("integration-test --duration 10 --out {out} --model rom --option model={bad}/missing.npz",
     "model: must be an existing model file"),
    ("integration-test --duration 10 --out {out} --config {bad}/missing.toml",
     "--config: must be an existing TOML file"),
    ("integration-test --duration 10 --out {out} --config {bad}/latin1.toml",
     "--config: must be a UTF-8 text file"),
    ("serve-800xa --config {bad}/missing.toml", "config: must be an existing TOML file"),
    ("serve-800xa --config {bad}/latin1.toml", "config: must be a UTF-8 text file"),
    ("serve-800xa --speed -3", "speed: must be in"),
    ("serve-800xa --port 99999", "port: must be in [1, 65535]"),
    ("stockpile --server nothttp", "server: must be an opc.tcp:// URL"),
    ("stockpile --server opc.tcp://127.0.0.1:1 --model foo", "model: must be one of"),
    ("stockpile --server opc.tcp://127.0.0.1:1 --password-file {bad}/missing",
     "password_file: must be an existing file"),
    ("stockpile --server opc.tcp://127.0.0.1:1 --period -1", "period: must be in (0, 3600] s"),
    ("monitor --stockpile ftp://x", "stockpile: must be an http:// or https:// URL"),
    ("monitor --stockpile http://127.0.0.1:9 --port 70000", "port: must be an integer"),
    ("dem pile --particles -5 --out {out}", "--particles: must be in [1, 200000]"),
    ("dem pile --particles 1e9 --out {out}", "--particles: invalid int value"),
    ("dem pile --particles 10 --out {out} --config {bad}/missing.toml",
     "dem config: must be an existing TOML file"),
    ("dem pile --particles 10 --out {out} --config {bad}/latin1.toml",
     "dem config: must be a UTF-8 text file"),
    ("dem discharge --from {bad}/missing --rate 100 --duration 1 --out {out}",
     "--from: must be a directory holding checkpoint.npz"),
    ("dem discharge --from {bad}/folder --rate 100 --duration 1 --out {out}",
     "--from: must be a directory holding checkpoint.npz"),
    ("dem discharge --from {bad}/missing.npz --rate 100 --duration 1 --out {out}",
     "--from: must be a directory holding checkpoint.npz or a checkpoint .npz file"),
    ("dem discharge --from {bad}/folder --rate 100 --duration 1 --out {out} --set friction",
     "--from: must be a directory holding checkpoint.npz"),
    ("rom train --data {bad}/missing --out {out}/m.npz", "data: must be a DOE directory"),
    ("rom train --data {bad}/folder --out {out}/m.npz", "data: must be a DOE directory"),
    ("rom train --data {bad}/folder --out {out}/m.npz --rom-seeds 3",
     "--rom-seeds: must be only with --validation"),
    ("rom train --data {bad}/folder --out {out}/m.npz --landing-spread -1",
     "landing_spread: must be finite and >= 0 m"),
    ("rom train --data {bad}/folder --out {out}/m.npz --dispersivity -1",
     "dispersivity: must be finite and >= 0 m"),
    ("rom train --data {design} --out {out}/m.npz --validation {bad}/folder",
     "validation: must be the data folder of an exported held-out design"),
    ("rom train --data {bad}/folder --out {out}/m.npz --hanging-limit 0.01",
     "--hanging-limit: must be only with --validation"),
    ("rom train --data {design} --out {out}/m.npz --validation {validation} "
     "--hanging-limit 1.5", "hanging_limit: must be finite and >= 0 and <= 1"),
    ("rom train --data {bad}/folder --out {out}/m.npz --select-by floor-excess",
     "--select-by: must be only with --validation"),
    ("rom train --data {bad}/folder --out {out}/m.npz --workers 2",
     "--workers: must be only with --validation"),
    ("rom train --data {design} --out {out}/m.npz --validation {validation} --workers 0",
     "--workers: must be >= 1"),
    ("rom evaluate --model {bad}/text.md --data {bad}/folder", "model: must be a MineTwin ROM"),
    ("rom evaluate --quick --workers 0 --out {out}", "--workers: must be >= 1"),
    ("fmus validate {bad}/missing.fmu", "no such file"),
    ("fmus build --model nothing", "--model: must be one of"),
    ("reference record {bad}/missing.toml --out {out}/r.csv", "scenario: must be an existing"),
    ("reference compare {scenario} {bad}/missing.csv", "reference: must be a [reference] table"),
    ("sizes --x50 -1", "x50: must be in (0, x_max=1) m"),
    ("sizes --b nan", "b: must be > 0"),
]


@pytest.mark.parametrize("line, expected", CASES, ids=[c[0].split(" {")[0] + f"-{k}"
                                                       for k, c in enumerate(CASES)])
def test_bad_input_exits_2_naming_the_argument_without_a_traceback(line, expected, bad,
                                                                   tmp_path, capsys):
    argv = line.format(bad=bad, out=tmp_path / "out", scenario=SCENARIO,
                       design=DESIGN, validation=VALIDATION).split()
    env_before = dict(os.environ)
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own refusals
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2, err
    assert expected in err, err
    assert "Traceback" not in err
    assert dict(os.environ) == env_before
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir()) \
        or line.startswith(("events export", "simulate")), "a refused command wrote outputs"


def test_a_read_never_writes_and_an_id_out_of_range_is_refused(bad, tmp_path, capsys):
    empty = tmp_path / "empty.sqlite"
    shutil.copy(bad / "empty.sqlite", empty)
    assert main(["events", "summary", str(empty)]) == 2
    assert empty.stat().st_size == 0                      # not turned into a database
    store = tmp_path / "events.sqlite"
    _events_store(store)
    before = store.read_bytes()
    assert main(["events", "history", str(store), str(2 ** 64)]) == 2
    assert "particle_id: must be an integer in [0, 9223372036854775807]" in capsys.readouterr().err
    assert main(["events", "history", str(store), "2"]) == 0
    assert store.read_bytes() == before
