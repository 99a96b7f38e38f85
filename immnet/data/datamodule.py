"""``LASTDataModule``: 3D-LAST data sets as Lightning batches of TensorDicts.

A batch is a ``TensorDict`` of batch size ``[B]`` with the data keys of ``immnet.keys`` (floats
float32, ``mode`` int64). One batch is one fancy-index read of the memmap (a batch sampler hands
the whole index list to ``__getitems__``; indices are sorted inside a batch for locality).

Splits: with ``test_data`` absent, a permutation seeded by ``split_seed`` puts
``round(test_fraction N)`` trajectories in test, ``round(val_fraction N)`` in validation, the rest
in train; with ``test_data`` given, the whole of it is the test split and ``data`` is split into
train and validation only; with ``val_data`` given too, the whole of it is the validation split and ``data`` is
all training data (real flights come split by flight: ``immnet data adsb``'s OUT/train, OUT/val, OUT/test).

A mixture (``data`` a list of data sets, e.g. 3D-LAST over a range of intervals and real flights at 1 s and
5 s): each set is split as above on its own (``val_data`` then a list as long as ``data``, an entry of null
taking ``val_fraction`` of its set; ``test_data`` one set for the whole mixture), and every batch holds the
trajectories of one set (sets differ in length ``T`` and interval), the sets' batches shuffled together each
pass (``_MixedBatches``; ``weights``, one per set, scale each set's batches a pass). One device only: the
distributed shards are per set.

Training batches may be augmented (``augment``, ``immnet.data.augment.FlightAugment``): each a fresh view of
its flights, turned about the radar site and measured again, seeded by the training step.

Stage 1 (``single_mode`` given, a mapping mode name -> data set of that mode): each training batch
is a ``TensorDict [M, B]``; row ``m`` is for expert ``m`` (``expert_modes[m]`` names its mode) and
holds ``round(own_fraction B)`` trajectories of its own mode followed by ``B - round(own_fraction B)``
maneuvering ones from the train split. Validation and test batches are always maneuvering ``[B]``.

Under a distributed strategy (``trainer.world_size > 1``, e.g. DDP) the module shards the batches
itself, and the CLI sets ``trainer.use_distributed_sampler`` to false: each rank reads its own
share of the train split (a ``DistributedSampler``, reshuffled per epoch), of the validation and
test splits (in order, padded to equal shares), and stage 1 draws its own-mode and maneuvering
streams per rank (seeded by rank). ``batch_size`` is per rank.

Resuming (``immnet fit --ckpt_path last``) sees the very batches an uninterrupted run sees: each
training pass is a function of its epoch alone (Lightning's ``set_epoch``, restored from the
checkpoint's loop state): the shuffled order is the ``RandomSampler``'s ``e``-th pass with the same
seed, the stage-1 streams are seeded by ``(split_seed, e)``, the distributed shards by
``DistributedSampler``'s epoch; and the training loader is stateful (Lightning saves its
``state_dict`` in every checkpoint), so that a run stopped part-way through a pass starts at the
first batch the training loop had not finished.
"""

from __future__ import annotations

import itertools
import math

import lightning as L
import torch
from tensordict import TensorDict
from torch.utils.data import BatchSampler, DataLoader, Dataset, DistributedSampler, SequentialSampler

from immnet import keys
from immnet.data.augment import FlightAugment
from immnet.data.contract import check_complete
from immnet.data.storage import as_batch, load_dataset, sample_digests
from immnet.motion import MODE_NAMES

SPLITS = ("train", "val", "test")


def _identity(batch):
    return batch


class TrajectoryDataset(Dataset):
    """Rows ``indices`` of a data set TensorDict; ``__getitems__`` reads a whole batch at once."""

    def __init__(self, td: TensorDict, indices: torch.Tensor):
        self.td, self.indices = td, indices

    def __len__(self) -> int:
        return len(self.indices)

    def __getitems__(self, idx) -> TensorDict:
        rows = self.indices[torch.as_tensor(idx, dtype=torch.long)].sort().values
        return as_batch(self.td[rows])

    def __getitem__(self, i) -> TensorDict:
        return self.__getitems__([i])[0]


class MixtureDataset(Dataset):
    """Several data sets' rows end to end: index ``offsets[k] + i`` is row ``i`` of part ``k``. A batch is read
    from one part (``_MixedBatches`` and the evaluation batches never mix parts)."""

    def __init__(self, parts: list[TrajectoryDataset]):
        self.parts = parts
        self.offsets = [0, *itertools.accumulate(len(part) for part in parts)]

    def __len__(self) -> int:
        return self.offsets[-1]

    def part_of(self, i: int) -> int:
        for k in range(len(self.parts)):
            if i < self.offsets[k + 1]:
                return k
        raise IndexError(f"index {i} out of range for a mixture of {len(self)} trajectories")

    def __getitems__(self, idx) -> TensorDict:
        idx = torch.as_tensor(idx, dtype=torch.long)
        k = self.part_of(int(idx.min()))
        if int(idx.max()) >= self.offsets[k + 1]:
            raise ValueError("a batch of a mixture must come from one of its data sets")
        return self.parts[k].__getitems__(idx - self.offsets[k])

    def __getitem__(self, i) -> TensorDict:
        return self.__getitems__([i])[0]


class _Epochs:
    """A sampler whose pass is a function of its epoch, which Lightning's ``set_epoch`` sets."""

    epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)


class _MixedBatches(_Epochs, torch.utils.data.Sampler):
    """Training batches of a mixture: pass ``e`` (``set_epoch``) shuffles each part's rows, cuts them into batches
    of ``batch_size`` (a part's last batch may be short) and shuffles the batches of all parts together, seeded
    by ``(seed, e)`` alone (resumable as ``_EpochRandomSampler``).

    ``weights`` (one per part, > 0, as ``LASTDataModule`` checks them; default 1): a part's batches per pass are
    ``round(weight x its batches)``, at least one, taken from as many fresh shuffles of its rows as they need (each
    cut as above), so a weight of 2 is the part listed twice and 0.5 half of its batches a pass; weights of 1 draw
    exactly the unweighted batches."""

    def __init__(self, sizes: list[int], batch_size: int, seed: int, weights: list[float] | None = None):
        self.sizes, self.batch_size, self.seed = list(sizes), int(batch_size), int(seed)
        self.counts = [max(1, round(w * math.ceil(n / self.batch_size)))
                       for w, n in zip(weights or [1.0] * len(self.sizes), self.sizes)]

    def __len__(self) -> int:
        return sum(self.counts)

    def __iter__(self):
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
        batches, offset = [], 0
        for n, count in zip(self.sizes, self.counts):
            part: list[list[int]] = []
            while len(part) < count:  # one shuffle of the part's rows, cut into batches, per round
                rows = (torch.randperm(n, generator=g) + offset).tolist()
                part += [rows[i : i + self.batch_size] for i in range(0, n, self.batch_size)]
            batches += part[:count]
            offset += n
        for j in torch.randperm(len(batches), generator=g).tolist():
            yield batches[j]


class _EpochRandomSampler(_Epochs, torch.utils.data.Sampler):
    """Pass ``e`` (``set_epoch(e)``) is exactly the ``e``-th pass of ``RandomSampler(range(n),
    generator=manual_seed(seed))`` (each full pass of it draws two permutations), whatever passes ran before."""

    def __init__(self, n: int, seed: int):
        self.n, self.seed = n, seed

    def __len__(self):
        return self.n

    def __iter__(self):
        g = torch.Generator().manual_seed(self.seed)
        for _ in range(2 * self.epoch):
            torch.randperm(self.n, generator=g)
        yield from torch.randperm(self.n, generator=g).tolist()


class _ResumableBatches:
    """A batch sampler whose next pass can start part-way: ``resume_at(epoch, k)`` drops the first ``k``
    batches of the next pass if it is pass ``epoch``. ``sampler`` is what Lightning's ``set_epoch`` reaches."""

    def __init__(self, batches):
        self.batches = batches
        self.sampler = getattr(batches, "sampler", batches)
        self.pass_epoch, self._resume = None, None

    def __len__(self):
        return len(self.batches)

    def resume_at(self, epoch: int, k: int) -> None:
        self._resume = (int(epoch), int(k))

    def __iter__(self):
        self.pass_epoch = int(getattr(self.sampler, "epoch", 0))
        skip = self._resume[1] if self._resume is not None and self._resume[0] == self.pass_epoch else 0
        self._resume = None
        yield from itertools.islice(self.batches, skip, None)


class ResumableLoader(DataLoader):
    """The training loader, with Lightning's loader-state protocol (``state_dict`` / ``load_state_dict``):
    the epoch of the current pass and the batches of it the training loop has finished (``position()``)."""

    def __init__(self, dataset, batches, position, **kwargs):
        super().__init__(dataset, batch_sampler=_ResumableBatches(batches), **kwargs)
        self.position = position

    def state_dict(self) -> dict:
        return {"epoch": self.batch_sampler.pass_epoch, "batches": int(self.position())}

    def load_state_dict(self, state: dict) -> None:
        if state.get("epoch") is not None:
            self.batch_sampler.resume_at(state["epoch"], state["batches"])


class _Stage1Sampler(_Epochs):
    """Per batch, per expert: indices of its own-mode set and of the maneuvering train split."""

    def __init__(self, own_sizes, n_train, n_own, n_mix, n_batches, seed, rank: int = 0):
        self.own_sizes, self.n_train = own_sizes, n_train
        self.n_own, self.n_mix, self.n_batches, self.seed = n_own, n_mix, n_batches, seed
        self.rank = rank

    def __len__(self):
        return self.n_batches

    @staticmethod
    def _stream(g, size, k, n_batches):
        """``n_batches`` draws of ``k`` indices from ``range(size)``, walking through permutations."""
        need = k * n_batches
        perms = [torch.randperm(size, generator=g) for _ in range(max(1, math.ceil(need / max(size, 1))))]
        return torch.cat(perms)[:need].view(n_batches, k)

    def __iter__(self):
        key = (self.seed, self.epoch) if self.rank == 0 else (self.seed, self.epoch, self.rank)
        g = torch.Generator().manual_seed(hash(key) & 0x7FFFFFFF)
        self.epoch += 1
        own = [self._stream(g, s, self.n_own, self.n_batches) for s in self.own_sizes]
        mix = [self._stream(g, self.n_train, self.n_mix, self.n_batches) for _ in self.own_sizes]
        for b in range(self.n_batches):
            yield [(m, own[m][b], mix[m][b]) for m in range(len(self.own_sizes))]


class _Stage1Dataset(Dataset):
    def __init__(self, own: list[TrajectoryDataset], train: TrajectoryDataset, keys):
        self.own, self.train, self.keys = own, train, list(keys)

    def __len__(self):
        return len(self.train)

    def __getitems__(self, plan) -> TensorDict:
        rows = []
        for m, own_idx, mix_idx in plan:  # expert m's own-mode rows, then its maneuvering ones
            parts = [ds.__getitems__(idx).select(*self.keys)
                     for ds, idx in ((self.own[m], own_idx), (self.train, mix_idx)) if len(idx)]
            rows.append(torch.cat(parts, 0))
        return torch.stack(rows, 0)


def check_flights(train: list, others: list) -> None:
    """Refuse a run that would train on a flight kept for validation or test: ``train`` and ``others`` are
    ``(path, meta)`` of the run's training sets and of its validation and test sets. Every real-flight set
    (``immnet data adsb``) names its whole partition (``meta["flights"]``), so a training set's flights are checked
    against the validation and test flights of each real-flight set of the same samples in the run, its own partition
    included: sets of one region written at different scan intervals may split the flights differently (docs/real-data.md,
    "One partition per region"). A ValueError names both sets, the count and a flight."""
    def real(sets):  # (path, meta, its samples' digests) of the sets that name flights (3D-LAST's do not)
        return [(p, m, sample_digests(m)) for p, m in sets if isinstance(m, dict) and isinstance(m.get("flights"), dict)]

    trains = real(train)
    everything = trains + real(others)
    for path, meta, digests in trains:
        trained = set(meta["flights"].get(meta.get("split"), []))
        for other_path, other, other_digests in everything:
            if not digests & other_digests:
                continue
            for split in [s for s in ("val", "test") if s != meta.get("split")]:
                seen = sorted(trained & set(other["flights"].get(split, [])))
                if seen:
                    raise ValueError(
                        f"{path} trains on {len(seen)} flight(s) that the set of {other_path} keeps for {split} (e.g. "
                        f"{seen[0]}): its sets split the flights otherwise. Write one set with `immnet data adsb "
                        f"--splits-from` the other (docs/real-data.md, \"One partition per region\"), or set "
                        f"allow_seen_flights: true to train on them anyway")


class LASTDataModule(L.LightningDataModule):
    """3D-LAST train / val / test loaders (see the module doc for the splits and stage-1 batches)."""

    def __init__(self, data, test_data=None, val_fraction: float = 0.1, test_fraction: float = 0.1, val_data=None,
                 batch_size: int = 100, num_workers: int = 0, split_seed: int = 0,
                 single_mode: dict | None = None, own_fraction: float = 0.6,
                 expert_modes: list[str] | None = None, augment: FlightAugment | None = None,
                 weights: list[float] | None = None, allow_seen_flights: bool = False):
        """``augment``: a fresh view of each training batch (``FlightAugment``: turned about the radar site, new
        measurement noise), seeded by the training step; validation and test batches as stored. ``weights``: with a
        mixture, one per data set, its training batches a pass relative to its size (``_MixedBatches``).
        ``allow_seen_flights``: train even where a real-flight training set holds flights that a set of the same
        samples in this run keeps for validation or test (refused by default: ``check_flights``)."""
        super().__init__()
        self.allow_seen_flights = allow_seen_flights
        self.augment = augment
        sets = len(data) if isinstance(data, (list, tuple)) else 0  # weights are a mixture's (checked now, not at fit)
        if weights is not None and not (isinstance(weights, (list, tuple)) and len(weights) == sets
                                        and all(math.isfinite(float(w)) and float(w) > 0 for w in weights)):
            raise ValueError(f"weights must be one number > 0 per data set of the mixture ({sets}), got {weights!r}")
        self.weights = None if weights is None else [float(w) for w in weights]
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        for name, f in (("val_fraction", val_fraction), ("test_fraction", test_fraction),
                        ("own_fraction", own_fraction)):
            if not 0.0 <= f <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {f}")
        if test_data is None and val_fraction + test_fraction >= 1.0:
            raise ValueError("val_fraction + test_fraction must leave some training data")
        self.data, self.test_data, self.val_data = data, test_data, val_data
        self.val_fraction, self.test_fraction = val_fraction, test_fraction
        self.batch_size, self.num_workers, self.split_seed = batch_size, num_workers, split_seed
        self.single_mode = dict(single_mode) if single_mode else None
        self.own_fraction = own_fraction
        if self.single_mode:
            for name in self.single_mode:
                if name not in MODE_NAMES:
                    raise ValueError(f"single_mode key {name!r} is not a mode; valid: {', '.join(MODE_NAMES)}")
            expert_modes = list(expert_modes or [n for n in MODE_NAMES if n in self.single_mode])
            missing = [n for n in expert_modes if n not in self.single_mode]
            if missing:
                raise ValueError(f"expert_modes {missing} have no single_mode data set")
        self.expert_modes = expert_modes
        self._ready = False

    # --- data ---------------------------------------------------------------------------------
    def _paths(self) -> tuple[list, list]:
        """The data sets and their validation sets (None: ``val_fraction`` of the set), one of each per part."""
        data = list(self.data) if isinstance(self.data, (list, tuple)) else [self.data]
        if not data:
            raise ValueError("data is an empty list: give a data set or a list of them")
        if isinstance(self.val_data, (list, tuple)):
            vals = list(self.val_data)
            if len(vals) != len(data):
                raise ValueError(f"val_data lists {len(vals)} sets for {len(data)} data sets: give one per data set "
                                 "(null: val_fraction of that set) or a single set")
        elif self.val_data is not None and len(data) > 1:
            raise ValueError("with a mixture of data sets, val_data is a list with one entry per data set "
                             "(null: val_fraction of that set)")
        else:
            vals = [self.val_data] * len(data)
        return data, vals

    def _split(self, path, val_path, g: torch.Generator) -> dict:
        """One data set's splits: ``{split: (TensorDict, row indices)}``."""
        td, meta = load_dataset(path)
        n = td.batch_size[0]
        perm = torch.randperm(n, generator=g)
        n_test = 0 if self.test_data is not None else round(self.test_fraction * n)
        n_val = 0 if val_path is not None else round(self.val_fraction * n)
        if n - n_test - n_val < 1:
            raise ValueError(f"{n} trajectories of {path} leave no training data after the val/test split")
        parts = {"train": (td, perm[n_test + n_val :].sort().values),
                 "val": (td, perm[n_test : n_test + n_val].sort().values),
                 "test": (td, perm[:n_test].sort().values)}
        val_meta = None
        if val_path is not None:
            val_td, val_meta = load_dataset(val_path)
            parts["val"] = (val_td, torch.arange(val_td.batch_size[0]))
        return {"meta": meta, "val_meta": val_meta, "path": path, "val_path": val_path, **parts}

    def setup(self, stage: str | None = None) -> None:
        if self._ready:
            return
        data, vals = self._paths()
        if self.single_mode and len(data) > 1:
            raise ValueError("stage 1 (single_mode) takes one data set, not a mixture")
        g = torch.Generator().manual_seed(int(self.split_seed))
        self._parts = [self._split(p, v, g) for p, v in zip(data, vals)]
        self.meta = self._parts[0]["meta"]
        self._test = test_meta = None
        if self.test_data is not None:
            test_td, test_meta = load_dataset(self.test_data)
            self._test = (test_td, torch.arange(test_td.batch_size[0]))
        if not self.allow_seen_flights:
            check_flights([(p["path"], p["meta"]) for p in self._parts],
                          [(p["val_path"], p["val_meta"]) for p in self._parts if p["val_meta"] is not None]
                          + ([(self.test_data, test_meta)] if test_meta is not None else []))
        self._own = None
        if self.single_mode:
            td = self._parts[0]["train"][0]
            loaded = {name: load_dataset(path)[0] for name, path in self.single_mode.items()}
            T = td["measurements"].shape[1]
            for name, sm in loaded.items():
                if sm["measurements"].shape[1] != T:
                    raise ValueError(f"single-mode set {name!r} has T={sm['measurements'].shape[1]}, data has T={T}")
            self._own = [TrajectoryDataset(loaded[name], torch.arange(loaded[name].batch_size[0]))
                         for name in self.expert_modes]
            self._common_keys = sorted(set(td.keys()).intersection(*(sm.keys() for sm in loaded.values())))
        self._ready = True

    def dataset(self, name: str) -> TrajectoryDataset | MixtureDataset:
        if name not in SPLITS:
            raise ValueError(f"unknown split {name!r}; valid: {', '.join(SPLITS)}")
        self.setup()
        if name == "test" and self._test is not None:
            return TrajectoryDataset(*self._test)
        parts = [TrajectoryDataset(*part[name]) for part in self._parts]
        return parts[0] if len(parts) == 1 else MixtureDataset(parts)

    def split(self, name: str) -> TensorDict:
        """The whole split ``name`` (train / val / test) as an in-memory TensorDict [N_split]."""
        ds = self.dataset(name)
        if isinstance(ds, MixtureDataset):
            raise ValueError(f"split({name!r}) of a mixture: its data sets differ in length and interval, read each "
                             "set on its own (LASTDataModule(path).split(...))")
        return ds.__getitems__(torch.arange(len(ds)))

    def on_after_batch_transfer(self, batch, dataloader_idx: int):
        """Lightning's hook on every batch on its device: a training batch becomes ``augment``'s view of it for the
        trainer's global step (a resumed run sees the same views)."""
        if self.augment is not None and self.trainer is not None and self.trainer.training:
            return self.augment(batch, self.trainer.global_step)
        return batch

    # --- loaders ------------------------------------------------------------------------------
    def _loader(self, ds, sampler, train: bool = False) -> DataLoader:
        """The loader of ``ds`` by the batches of ``sampler``; ``train``: the resumable training loader."""
        kwargs = {"collate_fn": _identity, "num_workers": self.num_workers, "persistent_workers": self.num_workers > 0}
        if train:
            return ResumableLoader(ds, sampler, self._train_position, **kwargs)
        return DataLoader(ds, batch_sampler=sampler, **kwargs)

    def _train_position(self) -> int:
        """The training batches of the current pass the attached trainer has finished."""
        return self.trainer.fit_loop.epoch_loop.batch_progress.current.completed if self.trainer is not None else 0

    def _ranks(self) -> tuple[int, int]:
        """``(world_size, rank)`` of the attached trainer; ``(1, 0)`` without one."""
        return (self.trainer.world_size, self.trainer.global_rank) if self.trainer is not None else (1, 0)

    def _check_trainable(self) -> None:
        """Training and validation batches need truth and a label at every scan (contract.check_complete)."""
        if getattr(self, "_trainable", False):
            return
        self.setup()
        sets = [(f"data {part['path']}", part["train"][0]) for part in self._parts]
        sets += [(f"val_data {p['val_path']}", p["val"][0]) for p in self._parts if p["val_path"] is not None]
        sets += [(f"single-mode set {k!r}", o.td) for k, o in zip(self.expert_modes or (), self._own or ())]
        for name, td in sets:
            check_complete({k: td[k].numpy() for k in (keys.STATES, keys.MODE) if k in td.keys()}, name)
        self._trainable = True

    def train_dataloader(self) -> DataLoader:
        self._check_trainable()
        ds = self.dataset("train")
        world, rank = self._ranks()
        if isinstance(ds, MixtureDataset):
            if world > 1:
                raise ValueError("a mixture of data sets trains on one device (world size 1), not on "
                                 f"{world}: its batches are drawn per set")
            sizes = [len(p) for p in ds.parts]
            return self._loader(ds, _MixedBatches(sizes, self.batch_size, int(self.split_seed) + 1, self.weights), True)
        if not self.single_mode:
            if world > 1:
                sampler = DistributedSampler(ds, num_replicas=world, rank=rank, shuffle=True, seed=int(self.split_seed) + 1)
            else:
                sampler = _EpochRandomSampler(len(ds), int(self.split_seed) + 1)
            return self._loader(ds, BatchSampler(sampler, self.batch_size, drop_last=False), True)
        n_own = round(self.own_fraction * self.batch_size)
        sampler = _Stage1Sampler([len(o) for o in self._own], len(ds), n_own, self.batch_size - n_own,
                                 max(1, math.ceil(len(ds) / (self.batch_size * world))), self.split_seed, rank)
        return self._loader(_Stage1Dataset(self._own, ds, self._common_keys), sampler, True)

    def _eval_loader(self, name) -> DataLoader:
        ds = self.dataset(name)
        world, rank = self._ranks()
        if isinstance(ds, MixtureDataset):  # each set's batches in order, one set after another
            if world > 1:
                raise ValueError(f"a mixture of data sets is evaluated on one device (world size 1), not on {world}")
            batches = [list(range(a + i, min(a + i + self.batch_size, b)))
                       for a, b in zip(ds.offsets[:-1], ds.offsets[1:]) for i in range(0, b - a, self.batch_size)]
            return self._loader(ds, batches)
        sampler = (DistributedSampler(ds, num_replicas=world, rank=rank, shuffle=False) if world > 1
                   else SequentialSampler(ds))
        return self._loader(ds, BatchSampler(sampler, self.batch_size, drop_last=False))

    def val_dataloader(self) -> DataLoader:
        self._check_trainable()
        return self._eval_loader("val")

    def test_dataloader(self) -> DataLoader:
        return self._eval_loader("test")
