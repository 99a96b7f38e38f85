"""Several output corrections on one filter (``immnet.stages.correct.CorrectionEnsemble``, docs/immnet.md "The output
correction"): its estimate is the mean of what each member's network reports run alone, its velocity and covariance
are the filter's, knocked out it is its filter; ``immnet.training.export.join_corrections`` joins runs that share
their filter, and refuses runs that do not."""

import pytest
import torch

from immnet import keys
from immnet.checkpoints import add_checksum, load_checkpoint
from immnet.config import instantiate, load_yaml
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.data.storage import as_batch
from immnet.filters.methods import method_config
from immnet.motion import POS
from immnet.stages import IMMNet
from immnet.tracking.networks import frame_origin, to_local, to_world
from immnet.training.export import join_corrections
from immnet.tracking.tracker import Tracker, load_network

ONE = {"class_path": "immnet.stages.correct.OutputCorrection", "init_args": {"hidden": 16}}


def _base_config(r=None) -> dict:
    """``real-imm-singer``'s network (the shipped real network's filter), each track's r estimated."""
    config = load_yaml(method_config("real-imm-singer"))
    config = dict(instantiate(config).network().config)
    config["gain"] = {**config["gain"], "init_args": {**config["gain"]["init_args"], "r": r}}
    return config


def _members(n: int, seed: int = 0, **changes) -> list[IMMNet]:
    torch.manual_seed(seed)
    nets = []
    for _ in range(n):
        net = IMMNet(**{**_base_config(), **changes}, correction=ONE)
        for p in net.correct.parameters():
            torch.nn.init.normal_(p, std=0.3)  # each member a correction of its own, of a few metres
        nets.append(net.eval())
    return nets


def _z(n: int = 5, T: int = 40) -> torch.Tensor:
    z = as_batch(generate(n, seed=9, spec=DataSpec(T=T, min_segment=8)))[keys.MEASUREMENTS].double()
    z[1, 10:13] = float("nan")
    return z


def _save(net: IMMNet, path):
    torch.save(add_checksum({"state_dict": {f"net.{k}": v for k, v in net.state_dict().items()},
                             "hyper_parameters": {"net": net.config}}), path)
    return path


def _ensemble(members: list[IMMNet]) -> IMMNet:
    net = IMMNet(**_base_config(), correction={"class_path": "immnet.stages.correct.CorrectionEnsemble",
                                               "init_args": {"members": len(members), "hidden": 16}})
    for stage, member in zip(net.correct.members, members):
        stage.load_state_dict(member.correct.state_dict())
    return net.eval()


def test_the_ensemble_reports_the_mean_of_its_members_run_alone():
    """Position: the mean of the members' corrected positions (float64, to 1e-9 m); velocity, acceleration and the
    covariance: the filter's, exactly; knocked out: the filter; the streaming tracker as the rollout."""
    members = _members(3)
    z = _z()
    with torch.no_grad():
        alone = [m.double().rollout(z)[0][keys.STATE] for m in members]
        net = _ensemble(members).double()
        out, carry = net.rollout(z, return_cov=True)
        base = IMMNet(**_base_config()).double().eval().rollout(z, return_cov=True)[0]  # the filter, no correction
    assert max(float((a - alone[0]).abs().max()) for a in alone[1:]) > 0.5  # the members correct differently
    state = out[keys.STATE]
    pos = list(POS)
    torch.testing.assert_close(state[..., pos], torch.stack(alone).mean(0)[..., pos], rtol=0, atol=1e-9)
    rest = [i for i in range(9) if i not in pos]
    torch.testing.assert_close(state[..., rest], base[keys.STATE][..., rest], rtol=0, atol=0)
    torch.testing.assert_close(out[keys.STATE_COV], base[keys.STATE_COV], rtol=0, atol=0)
    assert carry.get(keys.OUTPUT_HIDDEN).shape == (z.shape[0], 3, 2, 16)
    single = _ensemble(members)  # float32, as a user's tracker runs
    with torch.no_grad():
        origin = frame_origin(single, z)  # the streaming tracker's frame: each track's first detection
        rolled = to_world(single.rollout(to_local(z, origin))[0][keys.STATE], origin)
        tracker = Tracker(single)
        streamed = torch.stack([tracker.step(z[:, t].float())[keys.FUSED] for t in range(z.shape[1])], 1)
    torch.testing.assert_close(streamed, rolled, rtol=0, atol=1e-4)
    with torch.no_grad():
        knocked = net.knock_out("correction").rollout(z)[0][keys.STATE]
    torch.testing.assert_close(knocked, base[keys.STATE], rtol=0, atol=0)


def test_an_ensemble_of_one_is_refused():
    with pytest.raises(ValueError, match="at least 2 members"):
        IMMNet(**_base_config(), correction={"class_path": "immnet.stages.correct.CorrectionEnsemble",
                                             "init_args": {"members": 1}})


def test_join_corrections_writes_the_ensemble_of_its_runs(tmp_path):
    """Three runs' checkpoints joined: one file, its checksum, loading as the ensemble of their corrections."""
    members = _members(3, seed=1)
    paths = [_save(m, tmp_path / f"m{i}.ckpt") for i, m in enumerate(members)]
    out = join_corrections(paths, tmp_path / "joined.ckpt")
    assert load_checkpoint(out)["hyper_parameters"]["net"]["correction"] == {
        "class_path": "immnet.stages.correct.CorrectionEnsemble", "init_args": {"members": 3, "hidden": 16}}
    z = _z().float()
    with torch.no_grad():
        joined = load_network(out).rollout(z)[0][keys.STATE]
        expected = _ensemble(members).rollout(z)[0][keys.STATE]
    torch.testing.assert_close(joined, expected, rtol=0, atol=0)


def test_join_corrections_refuses_runs_on_other_filters(tmp_path):
    """Runs whose filters differ, in their arguments or their weights, or a network without a single correction,
    are refused by name, and nothing is written."""
    a = _save(_members(1, seed=2)[0], tmp_path / "a.ckpt")
    other = _save(_members(1, seed=3, p_stay=0.95)[0], tmp_path / "other.ckpt")
    with pytest.raises(ValueError, match=r"other.ckpt is not the network of .*a.ckpt with another correction: p_stay"):
        join_corrections([a, other], tmp_path / "out.ckpt")
    moved = _members(1, seed=4)[0]
    with torch.no_grad():
        moved.predict.F.add_(1e-3)
    moved = _save(moved, tmp_path / "moved.ckpt")
    with pytest.raises(ValueError, match=r"moved.ckpt: its weights outside the correction differ .*predict.F"):
        join_corrections([a, moved], tmp_path / "out.ckpt")
    plain = IMMNet(**_base_config())
    plain = _save(plain, tmp_path / "plain.ckpt")
    with pytest.raises(ValueError, match="plain.ckpt: its network has no single output correction"):
        join_corrections([a, plain], tmp_path / "out.ckpt")
    with pytest.raises(ValueError, match="at least 2 checkpoints"):
        join_corrections([a], tmp_path / "out.ckpt")
    assert not (tmp_path / "out.ckpt").exists()
