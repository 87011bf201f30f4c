"""The trainer's data: the datasets a :class:`TrainConfig` selects and the seeded step sampler."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
from torch.utils.data import Dataset, Sampler

from ..config import replace_config
from .config import TrainConfig


class StepSampler(Sampler[int]):
    """Infinite index stream: concatenated per-epoch permutations seeded by ``(seed, epoch)``.

    With ``group > 1`` an epoch is a random order of the blocks ``[0, group)``,
    ``[group, 2 group)``, ... each shuffled inside, so consecutive steps stay in one block
    (for the synthetic data: one rendered scene, reused from the dataset's memory cache).

    Args:
        length: dataset size.
        seed: run seed.
        start: first stream position to yield (``step * batch_size`` when resuming).
        group: block size (1 = a plain permutation).
    """

    def __init__(self, length: int, seed: int, start: int = 0, group: int = 1) -> None:
        if length < 1:
            raise ValueError(f"cannot sample from an empty dataset (length {length})")
        if group < 1:
            raise ValueError(f"group must be >= 1, got {group}")
        self.length, self.seed, self.start, self.group = int(length), int(seed), int(start), int(group)

    def permutation(self, epoch: int) -> np.ndarray:
        """``[length]`` int64 sample order of ``epoch``."""
        rng = np.random.default_rng([self.seed, epoch])
        if self.group == 1:
            return rng.permutation(self.length)
        g, n = self.group, self.length
        starts = rng.permutation(-(-n // g)) * g
        return np.concatenate([s + rng.permutation(min(g, n - s)) for s in starts])

    def __iter__(self) -> Iterator[int]:
        epoch, offset = divmod(self.start, self.length)
        while True:
            for i in self.permutation(epoch)[offset:]:
                yield int(i)
            epoch, offset = epoch + 1, 0

    def __len__(self) -> int:  # DataLoader only uses it for len(loader); the stream is endless
        return 2**62


def build_datasets(config: TrainConfig) -> tuple[Dataset, Dataset | None]:
    """``(train, val)`` datasets selected by ``config.dataset`` (``val`` is ``None`` when off).

    Synthetic: ``SyntheticMVSDataset(config.data)``, its rendered scenes cached on disk in
    ``data.cache_dir`` or, when that is ``None``, in ``output_dir/scene_cache`` (a scene
    costs seconds to render and is reused by every epoch); validation uses
    ``data.seed + val_seed_offset`` (other scenes). MVSNet: ``config.mvsnet.scans`` and,
    when non-empty, ``config.mvsnet.val_scans``.
    """
    train_ds, val_ds = _build_supervised(config)
    if config.real_fraction > 0:
        from .real_dataset import MixedDataset, RealMVSDataset

        real = RealMVSDataset(config.real, cache_dir=Path(config.output_dir) / "real_cache")
        train_ds = MixedDataset(train_ds, real, config.real_fraction, config.seed)
    return train_ds, val_ds


def _build_supervised(config: TrainConfig) -> tuple[Dataset | None, Dataset | None]:
    """The supervised part of :func:`build_datasets` (train is ``None`` when ``real_fraction == 1``)."""
    need_train = config.real_fraction < 1.0
    if config.dataset == "synthetic":
        from ..synthetic import SyntheticMVSDataset

        data = config.data
        if data.cache_dir is None:
            data = replace_config(data, cache_dir=Path(config.output_dir) / "scene_cache")
        train_ds = SyntheticMVSDataset(data) if need_train else None
        val_ds = None
        if config.val_every > 0:
            val_cfg = replace_config(data, seed=data.seed + config.val_seed_offset)
            val_ds = SyntheticMVSDataset(val_cfg)
        return train_ds, val_ds
    from .mvsnet_dataset import MVSNetDataset

    train_ds = MVSNetDataset(config.mvsnet) if need_train else None
    val_ds = None
    if config.val_every > 0 and config.mvsnet.val_scans:
        val_ds = MVSNetDataset(config.mvsnet, scans=config.mvsnet.val_scans)
    return train_ds, val_ds
