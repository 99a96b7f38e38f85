"""A radar that knows its accuracy: ``load_network(r=...)``, ``Tracker.pretrained(r=...)``, ``immnet track --r`` and
``immnet evaluate --told-r`` give a network's filter experts the measurement std in place of each track's estimate
(docs/tracking.md, "A radar that knows its accuracy")."""

import csv

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from immnet import keys
from immnet.checkpoints import shipped
from immnet.cli import main
from immnet.filters.methods import build_method
from immnet.tracking import Tracker
from immnet.tracking.tracker import load_network

R = 12.0


def _tracks(n=3, T=40, dt=5.0, r=R, seed=3):
    """Straight and level tracks at 5 s scans (inside real-5s's 4.5-5.5 s), measured with std ``r``."""
    rng = np.random.default_rng(seed)
    t = dt * np.arange(T)
    v = rng.uniform(100, 200, (n, 1, 3)) * np.array([1.0, 1.0, 0.02])
    truth = rng.uniform(-20_000, 20_000, (n, 1, 3)) * np.array([1.0, 1.0, 0.0]) + 3_000 * np.array([0, 0, 1.0]) \
        + v * t[None, :, None]
    return truth, (truth + rng.normal(0, r, truth.shape)).astype(np.float32)


def test_one_r_for_every_track_is_the_told_r_of_each():
    """``r=12`` loaded is ``r="data"`` fed 12 m for every track, to the bit; estimated (the shipped way) it differs."""
    _, z = _tracks()
    z = torch.from_numpy(z)
    fixed = Tracker.pretrained("real-5s", r=R).track(z)["state"]
    told = Tracker.pretrained("real-5s", r="data").track(z, r=torch.full((3,), R))["state"]
    estimated = Tracker.pretrained("real-5s").track(z)["state"]
    assert torch.equal(fixed, told)
    assert (fixed - estimated).abs().max() > 1e-3


def test_step_takes_each_tracks_r_and_a_network_that_estimates_it_refuses_one():
    """``Tracker.step(z, r=...)`` is ``Tracker.track(r=...)`` scan by scan; an r handed to a network that estimates
    its own is refused by name, not ignored."""
    _, z = _tracks(n=2, T=10)
    r = torch.tensor([8.0, 20.0])
    told = Tracker.pretrained("real-5s", r="data")
    whole = told.track(torch.from_numpy(z), r=r)["state"]
    told.reset(2)
    steps = torch.stack([told.step(torch.from_numpy(z[:, k]), dt=5.0, r=r)[keys.FUSED] for k in range(10)], 1)
    torch.testing.assert_close(steps, whole, rtol=1e-5, atol=1e-3)
    estimating = Tracker.pretrained("real-5s")
    for call in (lambda: estimating.track(torch.from_numpy(z), r=r),
                 lambda: estimating.step(torch.from_numpy(z[:, 0]), r=r)):
        with pytest.raises(ValueError, match="estimates each track's measurement std itself"):
            call()


def test_the_filters_use_the_given_r_at_every_scan():
    """After each scan the carry's ``r^2`` is the given ``r``'s square (estimated, it is the third-difference running
    mean that tests/test_r_estimate.py holds to a float64 computation)."""
    _, z = _tracks(n=2, T=12, dt=5.0)
    tracker = Tracker.pretrained("real-5s", r=R)
    tracker.reset(2)
    for k in range(z.shape[1]):
        tracker.step(torch.from_numpy(z[:, k]), dt=5.0)
        np.testing.assert_allclose(tracker.carry.get(keys.NOISE_VAR).double().numpy(), R * R, rtol=1e-6)


def _write_csv(path, z, dt=5.0):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["track_id", "t", "x", "y", "z"])
        for i, track in enumerate(z):
            w.writerows([[f"t{i}", f"{dt * k:.2f}", *(repr(float(v)) for v in zk)] for k, zk in enumerate(track)])


def _read_xyz(path):
    with open(path, newline="") as f:
        return np.array([[float(r[c]) for c in ("x", "y", "z")] for r in csv.DictReader(f)])


def test_immnet_track_r_gives_the_network_and_a_told_filter_the_radars_accuracy(tmp_path, capsys):
    truth, z = _tracks()
    _write_csv(tmp_path / "in.csv", z)
    out = tmp_path / "out.csv"
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(out), "--weights", "real-5s",
                 "--r", str(R)]) == 0
    api = Tracker.pretrained("real-5s", r=R).track(torch.from_numpy(z), intervals=torch.full(z.shape[:2], 5.0))
    # float32 rounding of positions in each track's frame (up to 30 km from its first detection here: a few mm)
    np.testing.assert_allclose(_read_xyz(out), api["state"][..., [0, 3, 6]].reshape(-1, 3).numpy(), rtol=0,
                               atol=1e-2)
    # a filter told each track's r (the real-flight filters' r: data) refuses a CSV without --r, naming it
    capsys.readouterr()
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(out), "--method",
                 "real-imm-singer-5s"]) == 2
    assert "give the radar's with --r METRES" in capsys.readouterr().err
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(out), "--method", "real-imm-singer-5s",
                 "--r", str(R)]) == 0
    batch = TensorDict({keys.MEASUREMENTS: torch.from_numpy(z).double(), keys.DT: torch.full((3,), 5.0),
                        keys.R: torch.full((3,), R)}, batch_size=[3])
    ref = build_method("real-imm-singer-5s").track(batch)[keys.STATE][..., [0, 3, 6]].reshape(-1, 3).numpy()
    np.testing.assert_allclose(_read_xyz(out), ref, rtol=0, atol=1e-6)
    # told the truth's r, the filter's estimate is below the raw measurements' error (a physical check of what it read)
    err = lambda e: float(np.sqrt(((e.reshape(truth.shape) - truth)[:, 5:] ** 2).mean()))  # noqa: E731
    assert err(_read_xyz(out)) < 0.8 * err(z)


def test_a_network_told_r_refuses_a_csv_without_r_and_takes_one_with_it(tmp_path, capsys):
    """A checkpoint whose filter experts are told r (``r: data``) tracks a CSV only with ``--r``, as loaded with it."""
    from immnet.checkpoints import add_checksum
    from immnet.tracking.tracker import read_checkpoint

    config, state = read_checkpoint(shipped("real-5s"))  # the same weights, its filter experts told r
    assert config["gain"]["init_args"]["r"] is None
    config["gain"]["init_args"]["r"] = "data"
    told = tmp_path / "told.ckpt"
    torch.save(add_checksum({"state_dict": {f"net.{k}": v for k, v in state.items()},
                             "hyper_parameters": {"net": config}}), told)
    _, z = _tracks()
    _write_csv(tmp_path / "in.csv", z)
    out = tmp_path / "out.csv"
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(out), "--checkpoint", str(told)]) == 2
    assert "give the radar's with --r METRES" in capsys.readouterr().err and not out.exists()
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(out), "--checkpoint", str(told),
                 "--r", str(R)]) == 0
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(tmp_path / "ref.csv"), "--weights",
                 "real-5s", "--r", str(R)]) == 0
    np.testing.assert_allclose(_read_xyz(out), _read_xyz(tmp_path / "ref.csv"), rtol=0, atol=1e-6)


@pytest.mark.parametrize("value", ["0", "-3", "nan", "inf"])
def test_immnet_track_refuses_an_r_that_is_not_a_positive_number(tmp_path, capsys, value):
    _, z = _tracks(n=1, T=5)
    _write_csv(tmp_path / "in.csv", z)
    assert main(["track", "--input", str(tmp_path / "in.csv"), "--output", str(tmp_path / "o.csv"), "--r", value]) == 2
    assert "--r is the radar's measurement std in metres, a finite number > 0" in capsys.readouterr().err
    assert not (tmp_path / "o.csv").exists()


def test_evaluate_told_r_tells_the_networks_and_leaves_the_filters_as_configured():
    net = build_method("immnet-real-5s", told_r=True)
    assert net.net.start.told_r and keys.R in net.needs
    assert not build_method("immnet-real-5s").net.start.told_r
    _, z = _tracks()
    batch = TensorDict({keys.MEASUREMENTS: torch.from_numpy(z).double(), keys.DT: torch.full((3,), 5.0),
                        keys.R: torch.full((3,), R)}, batch_size=[3])
    told = net.track(batch)[keys.STATE]
    api = Tracker.pretrained("real-5s", r=R).track(torch.from_numpy(z))["state"].double()
    torch.testing.assert_close(told, api, rtol=0, atol=0)
    for name in ("real-imm-singer-5s", "imm-tuned"):  # a filter is as configured, told r or not
        torch.testing.assert_close(build_method(name, told_r=True).track(batch)[keys.STATE],
                                   build_method(name).track(batch)[keys.STATE], rtol=0, atol=0)


def test_a_measurement_std_needs_filter_experts(tmp_path):
    """The paper's KalmanNet experts learn their gain without a measurement model: an r for them is refused."""
    import lightning as L

    from immnet.training import Stage2Module

    module = Stage2Module(net={"model_set": "configs/model_sets/imm4.yaml"})
    trainer = L.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False, max_epochs=0)
    trainer.strategy.connect(module)
    trainer.save_checkpoint(tmp_path / "net.ckpt")
    with pytest.raises(ValueError, match="a measurement std needs filter experts"):
        load_network(tmp_path / "net.ckpt", r=5.0)
    assert load_network(shipped("real"), r=5.0).start.told_r is False
