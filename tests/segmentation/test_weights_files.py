"""The learned segmenters' weights files (svs_torch.segmentation.network_files): what a file that cannot be used
gets, in one line naming it, and when."""

from __future__ import annotations

import pytest
import torch

from svs_torch.core.checks import InputError
from svs_torch.segmentation import network_files
from svs_torch.segmentation.nearness import NearnessNet
from svs_torch.segmentation.network_files import load_obstacle_net, save_obstacle_net


def _nearness_file(tmp_path, edit=None, name="net.pt"):
    """A nearness weights file as train_nearness.py writes one (its head zero: the rule alone), edited by ``edit``."""
    path = tmp_path / name
    save_obstacle_net(path, NearnessNet(), {"note": "test"})
    if edit is not None:
        stored = torch.load(path, weights_only=True)
        edit(stored)
        torch.save(stored, path)
    return path


@pytest.mark.parametrize("layer, value", [("down1.0.weight", float("nan")), ("head.bias", float("inf"))])
def test_weights_holding_nan_or_inf_are_refused_naming_the_file(tmp_path, layer, value):
    """Found by an audit: a NaN in a hidden layer under the zero head loaded in silence (the network's pass is
    skipped, so a corrupted file passed for the rule); a NaN elsewhere made every pair an ERROR row naming no file."""
    path = _nearness_file(tmp_path, lambda stored: stored["state_dict"][layer].view(-1).__setitem__(0, value))
    with pytest.raises(InputError, match=f"^segmenter: '{path}': its weights hold NaN or inf \\({layer}: ") as error:
        load_obstacle_net(f"nearness:{path}")
    assert "\n" not in str(error.value)


def test_a_file_of_a_newer_format_says_so(tmp_path):
    path = _nearness_file(tmp_path, lambda stored: stored.__setitem__("format", "svs_torch.nearness_net/2"))
    with pytest.raises(InputError, match=f"^segmenter: '{path}' is in format svs_torch.nearness_net/2, which this "
                                         "svs_torch does not read \\(it reads svs_torch.nearness_net/1"):
        load_obstacle_net(f"nearness:{path}")


def test_a_setting_from_a_newer_version_is_named(tmp_path):
    """A newer svs_torch adds settings without a new format (older files take the defaults): such a file was refused
    with Python's "NearnessNetConfig.__init__() got an unexpected keyword argument 'bogus'"."""
    path = _nearness_file(tmp_path, lambda stored: stored["config"].__setitem__("bogus", 1))
    with pytest.raises(InputError, match=f"^segmenter: '{path}': its stored settings are refused \\(bogus: not a "
                                         "setting of this svs_torch \\(written by a newer one\\?\\)\\)$"):
        load_obstacle_net(f"nearness:{path}")


@pytest.mark.parametrize("kind, setting", [("nearness", "rule_gain"), ("nearness", "disparity_temperature"),
                                           ("learned", "disparity_temperature")])
def test_an_infinite_stored_setting_is_refused(tmp_path, kind, setting):
    """Found by an audit: a file whose rule_gain was inf gave NaN logits on every pair ("network: expected finite
    obstacle logits", naming no file); an infinite disparity_temperature made the stereo features a flat mean and
    the run went on."""
    from svs_torch.segmentation.network import ObstacleNet

    path = tmp_path / "net.pt"
    save_obstacle_net(path, NearnessNet() if kind == "nearness" else ObstacleNet(), {})
    stored = torch.load(path, weights_only=True)
    stored["config"][setting] = float("inf")
    torch.save(stored, path)
    with pytest.raises(InputError, match=f"^segmenter: '{path}': its stored settings are refused \\(.*"
                                         "disparity_temperature: expected (a )?positive finite value"):
        load_obstacle_net(f"{kind}:{path}")


def test_check_weights_file_reads_each_version_once(tmp_path, monkeypatch):
    path = _nearness_file(tmp_path)
    reads, real = [], network_files.load_obstacle_net
    monkeypatch.setattr(network_files, "load_obstacle_net", lambda segmenter: reads.append(segmenter) or real(segmenter))
    monkeypatch.setattr(network_files, "_NET_CACHE", {})
    check_weights_file = network_files.check_weights_file
    for _ in range(3):
        check_weights_file(f"nearness:{path}")
    check_weights_file("nearness")  # the shipped weights are not read here
    check_weights_file("otsu")
    assert reads == [f"nearness:{path}"]
    path.write_bytes(b"rewritten, not weights")
    with pytest.raises(InputError, match="is not a weights file"):
        check_weights_file(f"nearness:{path}")


def test_the_same_network_and_record_give_the_same_bytes(tmp_path):
    """Found by an audit: each file held its random temporary name (``.net.pt.azl2wex2/data.pkl``) as the prefix of
    its records, so a rerun with the same seed and record was another file, and git saw the shipped one change."""
    torch.manual_seed(0)
    net = NearnessNet()
    first, second = tmp_path / "a.pt", tmp_path / "b.pt"
    save_obstacle_net(first, net, {"seed": 0})
    save_obstacle_net(second, net, {"seed": 0})
    assert first.read_bytes() == second.read_bytes()
    assert isinstance(load_obstacle_net(f"nearness:{second}"), NearnessNet)


def test_a_save_killed_midway_leaves_the_old_file_and_nothing_else(tmp_path):
    """Found by an audit: a training run killed (SIGKILL) while writing left a hidden temporary file beside the
    weights (in the package's weights/ folder, for the shipped ones); the old file itself was kept, and still is."""
    import signal
    import subprocess
    import sys

    from conftest import REPO_ROOT

    path = _nearness_file(tmp_path)
    before = path.read_bytes()
    script = ("import sys, time, torch\n"
              "from svs_torch.segmentation.nearness import NearnessNet\n"
              "from svs_torch.segmentation.network_files import save_obstacle_net\n"
              "real = torch.save\n"
              "def stalled(obj, f, *args, **kwargs):\n"
              "    real(obj, f, *args, **kwargs); print('written', flush=True); time.sleep(60)\n"
              "torch.save = stalled\n"
              "save_obstacle_net(sys.argv[1], NearnessNet(), {'note': 'killed'})\n")
    child = subprocess.Popen([sys.executable, "-c", script, str(path)], stdout=subprocess.PIPE, text=True,
                             env={**__import__("os").environ, "PYTHONPATH": str(REPO_ROOT)})
    try:
        assert child.stdout.readline().strip() == "written"
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait()
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name] and path.read_bytes() == before


def test_a_diverged_network_is_not_written_over_good_weights(tmp_path):
    """Found by an audit: 'train_nearness.py --learning-rate 1e30 --out GOOD.pt' diverged and wrote its NaN weights
    over GOOD.pt ("weights written"), a file load_obstacle_net then refuses: the good weights were lost."""
    path = _nearness_file(tmp_path)
    before = path.read_bytes()
    net = NearnessNet()
    with torch.no_grad():
        net.head.weight.fill_(float("nan"))
    with pytest.raises(InputError, match=f"^network: its weights hold NaN or inf \\(head.weight: a diverged training "
                                         f"run\\?\\); '{path}' not written$"):
        save_obstacle_net(path, net, {"note": "diverged"})
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == [path.name]


@pytest.mark.parametrize("key, value", [("config", "channels=(8, 16, 16)"), ("state_dict", {0: torch.zeros(1)})],
                         ids=["config-text", "state-dict-numbered"])
def test_a_file_of_the_right_format_with_foreign_parts_is_refused_in_one_line(tmp_path, key, value):
    """Found by an audit: a settings text for the settings was Python's ValueError ("dictionary update sequence
    element #0 has length 1; 2 is required"; in svs-depth, "invalid segmenter_choice value"), and tensors under
    numbers an AttributeError traceback from inside torch's load_state_dict."""
    path = _nearness_file(tmp_path, lambda stored: stored.__setitem__(key, value))
    with pytest.raises(InputError, match=f"^segmenter: '{path}': the weights do not fit the network \\("):
        load_obstacle_net(f"nearness:{path}")
