"""Settings that are one of a few named kinds, read as types (immnet.choice): ``modes`` (immnet.motion.Modes),
``interaction`` (immnet.stages.filtering.Interaction) and a bank's ``likelihood`` / a rollout's ``return_loglik``
(immnet.stages.network.Likelihood). Each parser takes the configuration's spelling or the type and refuses anything
else in one line naming the setting, the value and the spellings; the type and its spelling build the same tracker,
whose configuration and hyper-parameters keep the plain spelling (a checkpoint loads with ``weights_only``)."""

import io
import json

import pytest
import torch
import yaml

from immnet import keys
from immnet.choice import Choice, spelled
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.filters.methods import build_method
from immnet.filters.multi import IMMFilter
from immnet.motion import ModelSet, Modes
from immnet.stages import IMMNet
from immnet.stages.filtering import FilterGain, FilterInteraction, Interaction
from immnet.stages.network import Likelihood
from immnet.tracking.bank import LIKELIHOODS, NetworkBank

ADAPTIVE = "configs/model_sets/imm4-adaptive.yaml"


@pytest.fixture(scope="module")
def z():
    td = generate(3, seed=7, spec=DataSpec(T=30, min_segment=10))
    z = td[keys.MEASUREMENTS].double()
    z[1, 12:14] = float("nan")  # missed detections
    return z


@pytest.fixture(scope="module")
def imm():
    return build_method("imm-tuned").network().float()


def test_each_setting_reads_its_spelling_or_its_type_and_is_written_as_its_spelling():
    for kind, spellings in ((Modes, ("joint", "axis", "channel")), (Interaction, ("fused", "imm")),
                            (Likelihood, ("filter", "reported"))):
        assert kind.spellings() == spellings
        for spelling in spellings:
            member = kind.parse(spelling)
            assert isinstance(member, kind) and kind.parse(member) is member and member.value == spelling
            assert member == spelling and str(member) == f"{member}" == spelling and json.dumps(member) == f'"{spelling}"'
    assert LIKELIHOODS == ("filter", "reported")
    assert Modes.JOINT.groups is None and Modes.JOINT.n_groups is None
    assert Modes.AXIS.groups == (0, 0, 0, 1, 1, 1, 2, 2, 2, 0) and Modes.AXIS.n_groups == 3
    assert Modes.CHANNEL.groups == (0, 0, 0, 0, 0, 0, 1, 1, 1, 0) and Modes.CHANNEL.n_groups == 2
    config = {"modes": Modes.AXIS, "gain": {"init_args": {"interaction": Interaction.IMM}}, "xs": [Likelihood.FILTER, 1]}
    plain = spelled(config)
    assert plain == {"modes": "axis", "gain": {"init_args": {"interaction": "imm"}}, "xs": ["filter", 1]}
    assert type(plain["modes"]) is str and type(plain["gain"]["init_args"]["interaction"]) is str
    assert yaml.safe_load(yaml.safe_dump(plain)) == plain


def _refused(make, message):
    with pytest.raises(ValueError) as err:
        make()
    assert str(err.value) == message and "\n" not in message


MODES_REFUSED = "modes must be one of ('joint', 'axis', 'channel'), got {}"
INTERACTION_REFUSED = "interaction must be one of ('fused', 'imm'), got {}"


@pytest.mark.parametrize("bad", ["plane", "Axis", 3, None, ["axis"], Interaction.IMM],
                         ids=["spelling", "case", "int", "none", "list", "other-type"])
def test_modes_refuses_a_wrong_spelling_or_type_in_one_line(bad):
    ms = ModelSet.from_config(ADAPTIVE)
    message = MODES_REFUSED.format(repr(bad))
    _refused(lambda: Modes.parse(bad), message)
    _refused(lambda: IMMNet(model_set=ADAPTIVE, modes=bad), message)
    _refused(lambda: FilterGain(ms, modes=bad), message)
    _refused(lambda: FilterInteraction(ms, modes=bad), message)
    _refused(lambda: IMMFilter(ModelSet([m for m in ms if not m.state_dependent]), 1.0, groups=bad),
             f"groups must be one of joint, axis, got {bad!r}")


def test_a_multi_target_imm_refuses_modes_per_channel_given_either_way():
    ms = ModelSet([m for m in ModelSet.from_config(ADAPTIVE) if not m.state_dependent])
    for bad in ("channel", Modes.CHANNEL):
        _refused(lambda: IMMFilter(ms, 1.0, groups=bad), f"groups must be one of joint, axis, got {bad!r}")


@pytest.mark.parametrize("bad", ["mixed", "IMM", 3, None, Modes.JOINT], ids=["spelling", "case", "int", "none",
                                                                           "other-type"])
def test_interaction_refuses_a_wrong_spelling_or_type_in_one_line(bad):
    """Refused by its own name first, also where a restart would need the IMM's interaction."""
    ms = ModelSet.from_config(ADAPTIVE)
    message = INTERACTION_REFUSED.format(repr(bad))
    _refused(lambda: Interaction.parse(bad), message)
    _refused(lambda: FilterInteraction(ms, interaction=bad), message)
    _refused(lambda: FilterInteraction(ms, interaction=bad, restart="data"), message)
    _refused(lambda: FilterGain(ms, interaction=bad), message)


@pytest.mark.parametrize("bad", ["best", "Reported", 3, None, Modes.JOINT],
                         ids=["spelling", "case", "int", "none", "other-type"])
def test_a_banks_likelihood_refuses_a_wrong_spelling_or_type_in_one_line(bad, imm):
    message = f"a bank's likelihood is one of filter, reported, got {bad!r}"
    _refused(lambda: Likelihood.parse(bad), message)
    _refused(lambda: NetworkBank({"a": imm}, likelihood=bad), message)


@pytest.mark.parametrize("bad", ["best", "Reported", 3, 1.0, Modes.JOINT],
                         ids=["spelling", "case", "int", "float", "other-type"])
def test_a_rollouts_return_loglik_refuses_a_wrong_spelling_or_type_in_one_line(bad, imm, z):
    """Before the likelihood was a type, any truthy ``return_loglik`` that was not ``"reported"`` gave the filter's
    likelihood."""
    _refused(lambda: imm.rollout(z.float(), return_loglik=bad),
             f"return_loglik must be False, True or one of ('filter', 'reported'), got {bad!r}")


def _network(modes, interaction):
    gain = {"class_path": "immnet.stages.filtering.FilterGain", "init_args": {
        "interaction": interaction, "onset": False, "model_noise": 0.3, "r": 30.0, "start_acc_std": 10.0}}
    bayes = {"class_path": "immnet.stages.BayesianModeUpdate", "init_args": {"from_experts": True}}
    return IMMNet(model_set=ADAPTIVE, gain=gain, classifier=bayes, p_stay=0.98, modes=modes).double().eval()


@pytest.mark.parametrize("modes", ["joint", "channel"])
def test_the_type_and_its_spelling_build_the_same_network(modes, z):
    """The same outputs, bit for bit, and the same configuration of plain strings: saved and loaded with
    ``weights_only`` (no class of the file's to run), written as YAML."""
    spelt = _network(modes, "imm")
    typed = _network(Modes.parse(modes), Interaction.IMM)
    assert typed.modes is Modes.parse(modes) and typed.interact.interaction is Interaction.IMM
    assert typed.config == spelt.config
    buf = io.BytesIO()
    torch.save({"hyper_parameters": {"net": typed.config}}, buf)
    buf.seek(0)
    assert torch.load(buf, weights_only=True)["hyper_parameters"]["net"] == spelt.config
    assert yaml.safe_load(yaml.safe_dump(typed.config)) == spelt.config
    if modes != "joint":
        assert type(typed.config["modes"]) is str
    assert type(typed.config["gain"]["init_args"]["interaction"]) is str
    with torch.no_grad():
        for asked in ((True, Likelihood.FILTER, "filter"), ("reported", Likelihood.REPORTED)):
            outs = [net.rollout(z, return_cov=True, return_loglik=a)[0] for net in (spelt, typed) for a in asked]
            for out in outs[1:]:
                for key in (keys.STATE, keys.STATE_COV, keys.LOGLIK, keys.ROLLOUT_EXPERT_PROBS):
                    assert torch.equal(out[key].nan_to_num(), outs[0][key].nan_to_num())
            assert torch.isfinite(outs[0][keys.LOGLIK]).any()


def test_a_module_built_from_a_typed_mapping_saves_the_spellings():
    """A training module's hyper-parameters (what a checkpoint holds) keep the spellings of a network given as a
    mapping holding the types."""
    from immnet.training import Stage2Module

    spelt = _network("channel", "imm").config
    typed = dict(spelt, modes=Modes.CHANNEL,
                 gain={**spelt["gain"], "init_args": {**spelt["gain"]["init_args"], "interaction": Interaction.IMM}})
    module = Stage2Module(net=typed)
    assert module.hparams["net"] == spelt and type(module.hparams["net"]["modes"]) is str
    assert type(module.hparams["net"]["gain"]["init_args"]["interaction"]) is str
    assert module.net.modes is Modes.CHANNEL


def test_a_bank_weighs_the_same_with_the_likelihood_given_either_way(z):
    nets = {n: build_method(n).network().float() for n in ("imm-tuned", "imm-min")}
    outs = []
    for likelihood in ("filter", Likelihood.FILTER):
        bank = NetworkBank(nets, prior=[0.4, 0.6], likelihood=likelihood)
        assert bank.likelihood is Likelihood.FILTER and "likelihood 'filter'" in repr(bank)
        outs.append(bank.track(z.float(), return_cov=True))
    for key in (keys.STATE, keys.STATE_COV, keys.MEMBER_PROBS):
        assert torch.equal(outs[0][key].nan_to_num(), outs[1][key].nan_to_num())


def test_a_multi_target_imm_per_axis_is_the_same_given_either_way():
    ms = ModelSet([m for m in ModelSet.from_config(ADAPTIVE) if not m.state_dependent])
    plots = torch.tensor([[1000.0, 2000.0, 3000.0], [-500.0, 800.0, 1200.0]], dtype=torch.float64)
    R = torch.eye(3, dtype=torch.float64).expand(2, 3, 3) * 900.0
    results = []
    for groups in ("axis", Modes.AXIS):
        f = IMMFilter(ms, 1.0, groups=groups)
        assert f.groups is Modes.AXIS and "modes axis" in repr(f)
        f.start(plots.numpy(), R.numpy())
        results.append(f.predict(5.0))
    for a, b in zip(*results):
        assert (a == b).all()


def test_every_choice_is_a_str_enum_with_its_own_members():
    for kind in (Modes, Interaction, Likelihood):
        assert issubclass(kind, Choice) and issubclass(kind, str)
    assert Modes.lookup(Interaction.IMM) is None and Interaction.lookup("joint") is None
