"""LASTDataModule: split sizes and disjointness, batch layout, stage-1 mixing."""

import pytest
import torch

from immnet.data import LASTDataModule, write_dataset
from immnet.data.datamodule import MixtureDataset
from immnet.data.spec import DataSpec

SPEC = DataSpec(T=40, min_segment=10)


@pytest.fixture(scope="module")
def sets(tmp_path_factory):
    d = tmp_path_factory.mktemp("dm")
    paths = {"main": write_dataset(d / "main", 1000, 0, SPEC), "test": write_dataset(d / "test", 120, 9, SPEC)}
    for i, m in enumerate(("cv", "ca", "ct+", "ct-")):
        paths[m] = write_dataset(d / m, 150, 100 + i, SPEC, single_mode=m)
    return paths


def _ids(td):
    """Identify trajectories by their first true position."""
    return {tuple(x) for x in td["states"][:, 0, [0, 3, 6]].tolist()}


def test_split_sizes_disjoint_and_deterministic(sets):
    dm = LASTDataModule(sets["main"], val_fraction=0.1, test_fraction=0.2, batch_size=64, split_seed=3)
    tr, va, te = dm.split("train"), dm.split("val"), dm.split("test")
    assert (tr.batch_size[0], va.batch_size[0], te.batch_size[0]) == (700, 100, 200)
    a, b, c = _ids(tr), _ids(va), _ids(te)
    assert len(a | b | c) == 1000 and not (a & b) and not (a & c) and not (b & c)
    again = LASTDataModule(sets["main"], val_fraction=0.1, test_fraction=0.2, split_seed=3)
    assert _ids(again.split("test")) == c
    other = LASTDataModule(sets["main"], val_fraction=0.1, test_fraction=0.2, split_seed=4)
    assert _ids(other.split("test")) != c
    with pytest.raises(ValueError, match="split"):
        dm.split("holdout")


def test_batches_are_tensordicts(sets):
    dm = LASTDataModule(sets["main"], test_data=sets["test"], batch_size=64)
    assert dm.split("test").batch_size[0] == 120 and dm.split("train").batch_size[0] == 900
    batches = list(dm.train_dataloader())
    assert len(batches) == 15 and batches[0].batch_size == torch.Size([64]) and batches[-1].batch_size == torch.Size([4])
    b = batches[0]
    assert b["states"].dtype == torch.float32 and b["mode"].dtype == torch.int64
    assert b["measurements"].shape == (64, 40, 3)
    assert b["t"].dtype == torch.float64 and torch.equal(b["t"], torch.arange(40.0, dtype=torch.float64).expand(64, 40))
    seen = set().union(*(_ids(x) for x in batches))
    assert seen == _ids(dm.split("train"))  # an epoch covers the train split once
    v = next(iter(dm.val_dataloader()))
    assert v.batch_size == torch.Size([64])
    assert sum(x.batch_size[0] for x in dm.test_dataloader()) == 120


def test_stage1_batches_mix_own_mode_and_maneuvering(sets):
    modes = ["cv", "ca", "ct+", "ct-"]
    dm = LASTDataModule(sets["main"], batch_size=50, own_fraction=0.6, expert_modes=modes,
                        single_mode={m: sets[m] for m in modes})
    own_ids = [_ids(LASTDataModule(sets[m], val_fraction=0, test_fraction=0).split("train")) for m in modes]
    train_ids = _ids(dm.split("train"))
    loader = dm.train_dataloader()
    assert len(loader) == 16  # ceil(800 / 50)
    for k, batch in enumerate(loader):
        assert batch.batch_size == torch.Size([4, 50])
        for m in range(4):
            row = _ids(batch[m])
            first = {tuple(x) for x in batch[m, :30]["states"][:, 0, [0, 3, 6]].tolist()}
            rest = {tuple(x) for x in batch[m, 30:]["states"][:, 0, [0, 3, 6]].tolist()}
            assert first <= own_ids[m] and rest <= train_ids and len(row) == 50
            assert (batch[m, :30]["mode"][:, 0] == m).all()
        if k == 3:
            break
    v = next(iter(dm.val_dataloader()))
    assert v.batch_size == torch.Size([50])
    with pytest.raises(ValueError, match="no single_mode"):
        LASTDataModule(sets["main"], single_mode={"cv": sets["cv"]}, expert_modes=["cv", "ca"])


class _FakeTrainer:
    def __init__(self, world_size, global_rank):
        self.world_size, self.global_rank = world_size, global_rank


def _ranked(sets, rank, world=2, **kwargs):
    dm = LASTDataModule(sets["main"], val_fraction=0.1, test_fraction=0.2, batch_size=64, split_seed=3, **kwargs)
    dm.trainer = _FakeTrainer(world, rank)
    return dm


def test_ranks_share_out_the_train_split_and_cover_validation(sets):
    """Under DDP each rank reads its own share: the train shares are disjoint and cover the
    split; the validation shares cover it (the shorter share padded)."""
    whole = LASTDataModule(sets["main"], val_fraction=0.1, test_fraction=0.2, batch_size=64, split_seed=3)
    shares = [[_ids(b) for b in _ranked(sets, r).train_dataloader()] for r in (0, 1)]
    train = [set().union(*s) for s in shares]
    assert not train[0] & train[1]
    assert train[0] | train[1] == _ids(whole.split("train"))
    assert [len(s) for s in shares] == [6, 6]  # 700 / 2 ranks = 350 = 6 batches of <= 64 each
    val = [set().union(*(_ids(b) for b in _ranked(sets, r).val_dataloader())) for r in (0, 1)]
    assert val[0] | val[1] == _ids(whole.split("val"))


def test_ranks_draw_their_own_stage1_streams(sets):
    single = {m: sets[m] for m in ("cv", "ca", "ct+", "ct-")}
    first = [next(iter(_ranked(sets, r, single_mode=single).train_dataloader())) for r in (0, 1)]
    assert first[0].batch_size == first[1].batch_size == torch.Size([4, 64])
    assert _ids(first[0][0]) != _ids(first[1][0])
    # an epoch is one pass over the train split in all: each of 2 ranks draws half the batches
    alone = LASTDataModule(sets["main"], val_fraction=0.1, test_fraction=0.2, batch_size=64, split_seed=3,
                           single_mode=single)
    assert len(alone.train_dataloader()) == 11 and len(_ranked(sets, 0, single_mode=single).train_dataloader()) == 6


@pytest.mark.parametrize("pad", ["states", "mode"], ids=["truth-padded", "label-padded"])
def test_training_refuses_padded_tracks(tmp_path, pad):
    """Issue 20, items 2 and 3: padding (a NaN row of states, mode -1; docs/data.md) is accepted
    for evaluation but would make the training losses NaN (or index mode -1): the train and
    validation loaders refuse it by name, before any batch is drawn."""
    import numpy as np

    from immnet.data.generate import generate

    td = generate(20, seed=2, spec=DataSpec(T=50, min_segment=10))
    a = {k: td[k].numpy() for k in ("states", "measurements", "mode", "turn_rate", "r")}
    if pad == "states":
        a["states"][7, 30:] = np.nan
    else:
        a["mode"][7, 30:] = -1
    np.savez(tmp_path / "p.npz", dt=1.0, **a)
    dm = LASTDataModule(str(tmp_path / "p.npz"), batch_size=4)
    what = "no truth" if pad == "states" else "no label"
    for loader in (dm.train_dataloader, dm.val_dataloader):
        with pytest.raises(ValueError, match=rf"the scan at \[7, 30\] has {what} .*; training needs truth at every "
                                             rf"scan and a label at every scan or at none"):
            loader()
    assert len(dm.split("test")) > 0  # the evaluation side still takes the data


def test_an_unlabelled_set_trains_with_its_own_validation_set(tmp_path):
    """Real flights have no mode labels (-1 at every scan) and come split by flight: a set labelled nowhere
    trains (on the state loss alone), ``val_data`` is the whole validation split and ``data`` all training."""
    import numpy as np

    from immnet.data.generate import generate

    for name, seed, n in (("train", 2, 20), ("val", 3, 6)):
        td = generate(n, seed=seed, spec=DataSpec(T=50, min_segment=10))
        a = {k: td[k].numpy() for k in ("states", "measurements", "mode", "turn_rate", "r")}
        a["mode"][:] = -1
        np.savez(tmp_path / f"{name}.npz", dt=1.0, **a)
    dm = LASTDataModule(str(tmp_path / "train.npz"), val_data=str(tmp_path / "val.npz"), test_fraction=0.0, batch_size=4)
    assert len(dm.dataset("train")) == 20 and len(dm.dataset("val")) == 6
    assert sum(b.batch_size[0] for b in dm.train_dataloader()) == 20
    assert sum(b.batch_size[0] for b in dm.val_dataloader()) == 6


def test_a_training_pass_is_a_function_of_its_epoch(sets):
    """Issue 20, item 5: a resumed run sees the batches of an uninterrupted one. Pass `e` of the shuffled
    loader, set by Lightning's `set_epoch(e)` alone, is the `e`-th pass of torch's own `RandomSampler`
    with the same seed (as an uninterrupted run iterates it); the stage-1 streams likewise."""
    from torch.utils.data import BatchSampler, RandomSampler

    from lightning.fabric.utilities.data import _set_sampler_epoch

    dm = LASTDataModule(sets["main"], batch_size=64, split_seed=2)
    n = len(dm.dataset("train"))
    reference = BatchSampler(RandomSampler(range(n), generator=torch.Generator().manual_seed(3)), 64, drop_last=False)
    passes = [list(reference) for _ in range(3)]
    for e in (2, 0, 1):  # in any order, each from a fresh loader, as after a restart
        loader = dm.train_dataloader()
        _set_sampler_epoch(loader, e)
        assert list(loader.batch_sampler) == passes[e]
    modes = ["cv", "ca", "ct+", "ct-"]
    stage1 = LASTDataModule(sets["main"], batch_size=20, expert_modes=modes, single_mode={m: sets[m] for m in modes})
    one_run = stage1.train_dataloader().batch_sampler
    run = [[[(m, o.tolist(), x.tolist()) for m, o, x in b] for b in one_run] for _ in range(2)]
    loader = stage1.train_dataloader()
    _set_sampler_epoch(loader, 1)
    assert [[(m, o.tolist(), x.tolist()) for m, o, x in b] for b in loader.batch_sampler] == run[1] != run[0]


def test_the_training_loader_resumes_part_way_through_a_pass(sets):
    """Issue 20, item 5: the training loader's state (Lightning's loader-state protocol) says which
    pass and how many of its batches were finished; a fresh loader given it starts at the next batch,
    in that pass only (the following pass is whole)."""
    dm = LASTDataModule(sets["main"], batch_size=64, split_seed=2)
    loader = dm.train_dataloader()
    loader.batch_sampler.sampler.set_epoch(1)
    whole = list(loader.batch_sampler)
    assert loader.state_dict() == {"epoch": 1, "batches": 0}  # no trainer attached: nothing finished
    fresh = dm.train_dataloader()
    fresh.load_state_dict({"epoch": 1, "batches": 5})
    fresh.batch_sampler.sampler.set_epoch(1)
    assert list(fresh.batch_sampler) == whole[5:]
    assert list(fresh.batch_sampler) == whole  # the next pass (same epoch here) starts at its first batch
    other = dm.train_dataloader()
    other.load_state_dict({"epoch": 1, "batches": 5})
    other.batch_sampler.sampler.set_epoch(2)  # a state of another pass does not cut this one
    assert len(list(other.batch_sampler)) == len(whole)
    got = [b["states"] for b in fresh]
    assert len(got) == len(whole) and torch.equal(got[0], dm.dataset("train").__getitems__(whole[0])["states"])


def test_a_mixture_draws_each_batch_from_one_set(sets, tmp_path):
    """``data`` as a list (3D-LAST beside real flights, each of its own length and interval): each set is split on
    its own (``val_data`` one entry per set, null: ``val_fraction`` of it), a batch holds one set's trajectories,
    a pass covers every training trajectory once, and pass ``e`` is a function of ``(split_seed, e)`` alone."""
    from lightning.fabric.utilities.data import _set_sampler_epoch

    short = write_dataset(tmp_path / "short", 90, 5, DataSpec(T=25, min_segment=8))
    val = write_dataset(tmp_path / "short-val", 13, 6, DataSpec(T=25, min_segment=8))
    dm = LASTDataModule([sets["main"], short], val_data=[None, val], val_fraction=0.1, test_fraction=0.0,
                        batch_size=32, split_seed=2)
    assert isinstance(dm.dataset("train"), MixtureDataset) and len(dm.dataset("train")) == 900 + 90 and len(dm.dataset("val")) == 100 + 13
    main_train = _ids(LASTDataModule(sets["main"], val_fraction=0.1, test_fraction=0.0, split_seed=2).split("train"))
    seen, lengths = set(), []
    loader = dm.train_dataloader()
    assert len(loader) == 29 + 3
    for batch in loader:
        T = batch["measurements"].shape[1]
        lengths.append(T)
        ids = _ids(batch)
        assert not (ids & seen)
        seen |= ids
        if T == 40:  # the first set's training split as alone
            assert ids <= main_train
    assert len(seen) == 990 and sorted(set(lengths)) == [25, 40]
    assert lengths != sorted(lengths) and lengths != sorted(lengths, reverse=True)  # the sets' batches shuffled together
    again = dm.train_dataloader()
    _set_sampler_epoch(again, 0)
    first = list(again.batch_sampler)
    _set_sampler_epoch(again, 1)
    assert list(again.batch_sampler) != first
    _set_sampler_epoch(again, 0)
    assert list(again.batch_sampler) == first
    val_T = [b["measurements"].shape[1] for b in dm.val_dataloader()]
    assert val_T == [40] * 4 + [25] and sum(b.batch_size[0] for b in dm.val_dataloader()) == 113
    with pytest.raises(ValueError, match="one entry per data set"):
        LASTDataModule([sets["main"], short], val_data=val).setup()
    with pytest.raises(ValueError, match="2 data sets"):
        LASTDataModule([sets["main"], short], val_data=[val]).setup()
    with pytest.raises(ValueError, match="read each set on its own"):
        dm.split("train")
    with pytest.raises(ValueError, match="one data set, not a mixture"):
        LASTDataModule([sets["main"], short], single_mode={"cv": sets["cv"]}).setup()


def test_a_mixtures_weights_scale_each_sets_batches_a_pass(sets, tmp_path):
    """``weights`` (one per set): a set's batches a pass are round(weight x its batches), each of its trajectories
    seen as often as the weight says (whole shuffles, then part of one); weights of 1 draw exactly the unweighted
    batches; a weight per set that is missing, zero or not finite is refused by name."""
    from immnet.data.datamodule import _MixedBatches

    plain = _MixedBatches([900, 90], 32, 3)
    assert list(_MixedBatches([900, 90], 32, 3, [1.0, 1.0])) == list(plain)  # the unweighted draw, to the row
    weighted = _MixedBatches([900, 90], 32, 3, [0.5, 3.0])
    assert weighted.counts == [14, 9] and len(list(weighted)) == 14 + 9  # round(0.5 x 29 batches), 3 x 3
    rows = [r for b in weighted for r in b]
    small = [r for r in rows if r >= 900]
    assert len(small) == 3 * 90 and {small.count(r) for r in set(small)} == {3}  # three whole shuffles
    big = [r for r in rows if r < 900]
    assert len(set(big)) == len(big) == 14 * 32  # 14 full batches of one shuffle, none repeated
    for b in weighted:
        assert all(r < 900 for r in b) or all(r >= 900 for r in b)  # a batch holds one set's rows

    short = write_dataset(tmp_path / "short", 90, 5, DataSpec(T=25, min_segment=8))
    dm = LASTDataModule([sets["main"], short], val_fraction=0.1, test_fraction=0.0, batch_size=32, split_seed=2,
                        weights=[1, 2])
    assert len(dm.train_dataloader()) == 29 + 2 * 3
    for bad in ([1.0], [1.0, 0.0], [1.0, float("nan")]):
        with pytest.raises(ValueError, match="weights must be one number > 0 per data set"):
            LASTDataModule([sets["main"], short], weights=bad)
    with pytest.raises(ValueError, match="weights must be one number > 0 per data set"):
        LASTDataModule(sets["main"], weights=[1.0])
