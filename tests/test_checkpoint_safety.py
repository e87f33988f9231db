"""Loading a checkpoint never runs code from it: a crafted pickle is refused naming the file and why, before
its payload runs; what warpgs writes is tensors and plain data, and older checkpoints still load."""
import io
import os
import random
from collections import OrderedDict

import numpy as np
import pytest
import torch

from train_fixtures import quick_overrides
from warpgs.cli.commands import train_main
from warpgs.train.checkpoint import (FORMAT, UnsafeCheckpointError, load_checkpoint, rng_state, save_checkpoint,
                                     set_rng_state)


class _TouchFile:
    """Unpickling this calls open(path, 'w'): a file appears if the loader ran it."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


class _System:
    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (os.system, (f"touch {self.path}",))


def _write_pickle(path, obj):
    buf = io.BytesIO()
    torch.save(obj, buf)
    path.write_bytes(buf.getvalue())
    return path


@pytest.mark.parametrize("payload", [_TouchFile, _System])
def test_crafted_checkpoint_is_refused_and_its_payload_never_runs(tmp_path, payload):
    marker = tmp_path / "payload-ran"
    path = _write_pickle(tmp_path / "checkpoint.pt", {"format": FORMAT, "version": 1, "step": 3,
                                                      "model": payload(marker)})
    with pytest.raises(UnsafeCheckpointError) as e:
        load_checkpoint(path)
    message = str(e.value)
    assert str(path) in message and "refused" in message and "arbitrary code" in message
    assert ("open" if payload is _TouchFile else "system") in message  # names what it would have called
    assert not marker.exists()


def test_object_arrays_are_refused_even_though_old_checkpoints_hold_numpy_arrays(tmp_path):
    marker = tmp_path / "payload-ran"
    path = _write_pickle(tmp_path / "c.pt", {"format": FORMAT, "version": 1,
                                             "a": np.array([_TouchFile(marker)], dtype=object)})
    with pytest.raises(UnsafeCheckpointError, match="ObjectDType"):
        load_checkpoint(path)
    assert not marker.exists()


def test_resume_from_a_crafted_checkpoint_is_a_clear_error(tmp_path, capsys):
    marker = tmp_path / "payload-ran"
    out = tmp_path / "run"
    out.mkdir()
    _write_pickle(out / "checkpoint.pt", {"format": FORMAT, "version": 1, "step": 3, "model": _TouchFile(marker)})
    assert train_main(quick_overrides(out, 5) + ["--resume", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "checkpoint.pt: refused to load" in err
    assert not marker.exists()


def test_truncated_checkpoint_is_unreadable_not_unsafe(tmp_path):
    path = save_checkpoint(tmp_path / "c.pt", {"step": 1, "x": torch.arange(1000.0)})
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"c\.pt: not a readable checkpoint") as e:
        load_checkpoint(path)
    assert not isinstance(e.value, UnsafeCheckpointError)


def test_saved_state_is_plain_data_and_round_trips(tmp_path):
    state = {"step": 7, "history": [{"psnr": np.float64(21.5), "n": np.int64(3)}],
             "strategy": OrderedDict(count=torch.ones(3), generator=torch.Generator().get_state()),
             "key": np.arange(4, dtype=np.uint32), "config": {"out": tmp_path, "betas": (0.9, 0.999)}}
    path = save_checkpoint(tmp_path / "c.pt", state)
    torch.load(path, weights_only=True)  # the plain loader accepts it without any allow-listing
    back = load_checkpoint(path)
    assert back["step"] == 7 and back["version"] == 2
    assert back["history"] == [{"psnr": 21.5, "n": 3}] and type(back["history"][0]["psnr"]) is float
    assert isinstance(back["strategy"], OrderedDict) and torch.equal(back["strategy"]["count"], torch.ones(3))
    assert torch.equal(back["key"], torch.arange(4)) and back["config"] == {"out": str(tmp_path),
                                                                           "betas": (0.9, 0.999)}


def test_unsavable_value_is_named_and_the_previous_checkpoint_kept(tmp_path):
    path = save_checkpoint(tmp_path / "c.pt", {"step": 1})
    before = path.read_bytes()
    with pytest.raises(TypeError, match=r"checkpoint\['extensions'\]\['0:x'\]\['hook'\]"):
        save_checkpoint(path, {"step": 2, "extensions": {"0:x": {"hook": lambda: None}}})
    assert path.read_bytes() == before


def _draws():
    return np.random.rand(3).tolist(), random.random(), torch.rand(3)


def test_rng_states_restore_exactly_from_new_and_version_1_checkpoints(tmp_path):
    state = rng_state()
    expected = _draws()
    path = save_checkpoint(tmp_path / "new.pt", {"rng": state})
    # Version 1 stored numpy's state as numpy's own tuple (a uint32 array inside): still loads, still exact.
    kind, key, pos, has_gauss, gauss = state["numpy"]
    old = dict(state, numpy=(kind, key.numpy().astype(np.uint32), pos, has_gauss, gauss))
    _write_pickle(tmp_path / "old.pt", {"format": FORMAT, "version": 1, "rng": old})
    set_rng_state(state)
    for name in ("new.pt", "old.pt"):
        _draws()  # move every generator on
        set_rng_state(load_checkpoint(tmp_path / name)["rng"])
        got = _draws()
        assert got[0] == expected[0] and got[1] == expected[1] and torch.equal(got[2], expected[2]), name
    assert not isinstance(load_checkpoint(path)["rng"]["numpy"][1], np.ndarray)
