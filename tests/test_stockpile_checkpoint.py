"""The stockpile checkpoint is data only: a crafted file runs no code.

The checkpoint used to be a pickle: a file that unpickles into ``os.system``
ran a command when the stockpile resumed. Now it is JSON plus raw numeric
arrays with a SHA-256 checksum (``surrogate.checkpoint``); these tests write
crafted checkpoints the way an attacker with write access to the state
folder would, and check that nothing runs and the error names the file.
"""

import hashlib
import json
import pickle
import sys
import warnings

import numpy as np
import pytest

from cosim.errors import ValidationError
from minetwin.cli import main
from surrogate.checkpoint import FORMAT, VERSION, CheckpointError, load_checkpoint, save_checkpoint
from surrogate.client import ClientOptions, ClientState, StockpileClient
from surrogate.stockpile import StockpileAsset


def _filled_state(model: str, options: dict) -> ClientState:
    asset = StockpileAsset(model, seed=3, storage_options=options)
    for k in range(8):
        asset.receive_bin(k + 1, 430.0, 0.01 + 0.001 * k, 1.0 + 0.1 * k, source=k % 2)
        asset.set_discharge_rate(120.0)
        asset.step(1.0)
    return ClientState(asset, last_applied=8, outflow_sequence=3,
                       outbox=[{"sequence": 3, "tracking_ids": [1], "masses": [1.5],
                                "grades": [0.01]}], heartbeat=17, ledger_id="abc")


def _run_on(asset: StockpileAsset) -> list:
    out = []
    for k in range(12):
        if k % 4 == 0:
            asset.receive_bin(100 + k, 300.0, 0.02, 1.2, source=1)
        asset.set_discharge_rate(150.0)
        step = asset.step(0.5)
        out.append((step["tracking_ids"].tolist(), step["masses"].tolist()))
    return out + [sorted(asset.held_by_tracking_id().items()), asset.totals()]


@pytest.fixture(scope="module")
def rom_file(tmp_path_factory):
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
    from test_rom_opcua import synthetic_rom

    return synthetic_rom().save(tmp_path_factory.mktemp("rom") / "synthetic.rom.npz")


@pytest.mark.parametrize("model", ["fifo", "mixing", "rom"])
def test_a_resumed_stockpile_goes_on_exactly_as_the_one_that_wrote_the_checkpoint(
        model, tmp_path, rom_file):
    options = {"model": str(rom_file)} if model == "rom" else {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # small piles are outside the ROM's training range
        state = _filled_state(model, options)
        path = tmp_path / "stockpile.checkpoint"
        save_checkpoint(path, state)
        loaded = load_checkpoint(path)
        assert isinstance(loaded, ClientState)
        assert (loaded.last_applied, loaded.outflow_sequence, loaded.heartbeat,
                loaded.ledger_id, loaded.outbox) == (8, 3, 17, "abc", state.outbox)
        if model == "mixing":  # the shared generator stays shared
            assert loaded.asset.storage.rng is loaded.asset.rng
        assert _run_on(loaded.asset) == _run_on(state.asset)


class _Payload:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (open, (str(self.marker), "w"))  # creating the marker file is "running code"


def _client(path):
    return StockpileClient(ClientOptions(server_url="opc.tcp://127.0.0.1:1/", checkpoint=path))


def test_the_client_names_the_sources_it_is_given_also_over_a_checkpoint(tmp_path):
    from minetwin.commands.stockpile import parse_source_names

    names = parse_source_names(["0=left source", "1=right source"])
    assert names == {0: "left source", 1: "right source"}
    with pytest.raises(ValidationError, match="source_name"):
        parse_source_names(["left=x"])
    path = tmp_path / "stockpile.checkpoint"
    client = _client(path)
    client.state.asset.receive_bin(1, 500.0, 0.01, 1.0, source=0)
    client.state.asset.receive_bin(2, 500.0, 0.01, 1.0, source=1)
    assert client.state.asset.origin_names() == {0: "source 0", 1: "source 1"}
    client._checkpoint()
    resumed = StockpileClient(ClientOptions(server_url="opc.tcp://127.0.0.1:1/",
                                            checkpoint=path, source_names=names))
    assert resumed.state.asset.origin_names() == names
    assert resumed.write_summary()["seed"] == 0  # the figures' titles name it


def test_a_crafted_pickle_checkpoint_runs_no_code_and_the_error_names_the_file(tmp_path):
    marker = tmp_path / "pwned"
    path = tmp_path / "stockpile.checkpoint"
    path.write_bytes(pickle.dumps(_Payload(marker)))
    with pytest.raises(CheckpointError, match=f"checkpoint: .*{path}: not a checkpoint"):
        _client(path)
    assert not marker.exists()


def _crafted(path, tree):
    body = json.dumps(tree).encode()
    header = {"format": FORMAT, "version": VERSION, "sha256": hashlib.sha256(body).hexdigest(),
              "tree_bytes": len(body), "arrays": []}
    path.write_bytes(json.dumps(header).encode() + b"\n" + body)


@pytest.mark.parametrize("target", ["os:system", "builtins:open", "subprocess:Popen",
                                    "minetwin.cli:main", "pickle:loads"])
def test_a_checkpoint_naming_a_class_outside_the_project_is_refused(tmp_path, target):
    path = tmp_path / "stockpile.checkpoint"
    _crafted(path, {"$obj": target, "attrs": {"args": "touch pwned"}})
    with pytest.raises(CheckpointError, match=f"{path}: unreadable contents"):
        load_checkpoint(path)
    assert not (tmp_path / "pwned").exists()


def test_an_object_array_or_a_corrupt_checkpoint_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "stockpile.checkpoint"
    save_checkpoint(path, _filled_state("fifo", {}))
    data = bytearray(path.read_bytes())
    data[-5] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match=f"{path}: checksum mismatch"):
        load_checkpoint(path)
    body = np.array([1], dtype=object)
    with pytest.raises(TypeError, match="only numeric arrays"):
        save_checkpoint(tmp_path / "other", body)
    header = {"format": FORMAT, "version": VERSION, "tree_bytes": 2,
              "arrays": [{"dtype": "|O", "shape": [1], "nbytes": 8}]}
    payload = b"{}" + bytes(8)
    header["sha256"] = hashlib.sha256(payload).hexdigest()
    path.write_bytes(json.dumps(header).encode() + b"\n" + payload)
    with pytest.raises(CheckpointError, match="array dtype object"):
        load_checkpoint(path)


def test_a_checkpoint_of_another_version_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "stockpile.checkpoint"
    save_checkpoint(path, _filled_state("fifo", {}))
    line, _, rest = path.read_bytes().partition(b"\n")
    header = json.loads(line)
    header["version"] = VERSION - 1
    path.write_bytes(json.dumps(header).encode() + b"\n" + rest)
    with pytest.raises(CheckpointError, match=f"{path}: version {VERSION - 1}, written by "
                                              "another MineTwin version"):
        load_checkpoint(path)


def test_the_stockpile_command_exits_2_on_a_bad_checkpoint(tmp_path, capsys):
    path = tmp_path / "stockpile.checkpoint"
    path.write_bytes(pickle.dumps(_Payload(tmp_path / "pwned")))
    password = tmp_path / "password"
    password.write_text("secret-password\n")
    code = main(["stockpile", "--server", "opc.tcp://127.0.0.1:1/", "--insecure",
                 "--password-file", str(password), "--checkpoint", str(path)])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert "error: checkpoint: must be a stockpile checkpoint" in err and str(path) in err
    assert not (tmp_path / "pwned").exists()
