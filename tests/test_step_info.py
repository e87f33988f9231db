"""StepInfo (train/step_info.py): the loss values of a training step's info are read on first use, once, and the
info otherwise behaves as the dict it is."""
import json

import torch

from warpgs.losses import LossResult
from warpgs.train.batch import HostScalars
from warpgs.train.step_info import DeviceFloats, StepInfo


def _info(ready=None):
    reads = []

    def read():
        reads.append(1)
        return {"loss": 0.5, "values": {"l1": 0.25}, "psnr": 20.0}

    return StepInfo({"step": 3, "num_primitives": 10, "stop": False}, read, ready=ready), reads


def test_plain_keys_do_not_read_and_a_loss_key_reads_once():
    info, reads = _info()
    assert info["step"] == 3 and info.get("stop") is False and "loss" in info
    info["language"] = {"a": 1.0}  # an extension adds a key
    assert reads == [] and info.pending
    assert info["loss"] == 0.5 and info.get("psnr") == 20.0 and info["values"] == {"l1": 0.25}
    assert reads == [1] and not info.pending


def test_iterating_copying_or_dumping_reads_every_key():
    for use in (list, dict, len, repr, lambda i: json.dumps(i), lambda i: i.copy(), lambda i: list(i.items())):
        info, reads = _info()
        use(info)
        assert reads == [1]
        assert set(info) == {"step", "num_primitives", "stop", "loss", "values", "psnr"}
    info, _ = _info()
    assert json.loads(json.dumps(info))["loss"] == 0.5
    assert info == {"step": 3, "num_primitives": 10, "stop": False, "loss": 0.5, "values": {"l1": 0.25},
                    "psnr": 20.0}


def test_ready_values_are_not_pending():
    info, reads = _info(ready=lambda: True)
    assert not info.pending and reads == []  # ready: reading would not wait, but nothing is read yet


def test_host_scalars_on_the_cpu_are_ready_and_give_the_summary():
    result = LossResult(torch.tensor(0.75), {"l1": torch.tensor(0.5), "dssim": torch.tensor(0.25)},
                        {"l1": 1.0, "dssim": 1.0})
    rgb, image = torch.full((2, 2, 3), 0.5), torch.full((2, 2, 3), 0.4)
    scalars = HostScalars(result, rgb, image)
    assert scalars.ready()
    s = scalars.summary()
    assert s["loss"] == 0.75 and s["values"] == {"l1": 0.5, "dssim": 0.25}
    assert abs(s["psnr"] - 20.0) < 1e-4  # MSE 0.01
    assert HostScalars(result).summary()["psnr"] is None


def test_an_extension_defers_its_own_keys_read_apart_from_the_loss():
    info, reads = _info(ready=lambda: True)
    lang_reads = []
    info.defer(("language",), lambda: lang_reads.append(1) or {"language": {"l_r": 0.1}}, ready=lambda: False)
    assert "language" in info and info.pending  # the extension's values are not ready
    assert info["language"] == {"l_r": 0.1} and lang_reads == [1] and reads == []
    assert not info.pending  # the loss values are ready (not read yet)
    assert info["loss"] == 0.5 and reads == [1] and lang_reads == [1]


def test_device_floats_read_once_as_python_floats():
    values = DeviceFloats({"a": torch.tensor(1.5), "b": torch.tensor(2, dtype=torch.int64)})
    assert values.ready() and values.read() == {"a": 1.5, "b": 2.0}
    assert DeviceFloats({}).read() == {}


def test_a_value_set_or_popped_is_not_overwritten_by_a_later_read():
    info, reads = _info()
    info["stop"] = True  # a plain key: nothing read
    assert reads == []
    info["loss"] = 9.0  # a deferred key: its group is read first, so the value set stays
    assert reads == [1] and info["loss"] == 9.0 and info["psnr"] == 20.0
    info2, _ = _info()
    assert info2.pop("psnr") == 20.0 and "psnr" not in info2 and info2["loss"] == 0.5
    info3, _ = _info()
    info3.update(loss=1.0)
    assert info3["loss"] == 1.0 and info3.setdefault("values") == {"l1": 0.25}
