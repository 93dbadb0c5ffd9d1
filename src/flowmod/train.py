"""Training of the 2-channel ResNet18 (Table 2 settings), seeded and resumable.

SGD (lr 0.01, momentum 0.9, weight decay 0.01), StepLR(step 10, gamma 0.5) stepped once per
epoch, batch 128, BCEWithLogitsLoss, random horizontal flip (mirror + negate u, on a copy)
with p = 0.5 on training batches only. Differences from the original code, on purpose: the
best epoch is chosen on the validation split only (one F1 over the whole split, ties -> the
earlier epoch) and reported elsewhere on test; no flips at evaluation; no still-object
thinning (that happens upstream, if at all).

Determinism: the model is initialised after ``torch.manual_seed(seed)``; each epoch's order
and flips come from a ``torch.Generator`` seeded with (seed, epoch), so a run resumed from
``last.pt`` draws exactly what an uninterrupted run draws. On CPU a model trains on
:data:`CPU_THREADS` torch thread (the caller's count is restored after), so the same seed
gives bit-identical weights and history (except ``seconds``) whatever the machine's core
count and whether other nodes train beside it (the driver trains ``n_jobs`` nodes at once,
:attr:`flowmod.dag.Stage.parallel`). On CUDA, deterministic algorithms are
requested (warn-only) and autocast (bf16, else fp16 with a GradScaler) is on by default, so
results are close but not guaranteed bit-identical.

Outputs in ``out_dir``: ``best.pt`` (state_dict of the best epoch), ``last.pt`` (checkpoint:
model, optimizer, scheduler, scaler, epoch, history, best, config, rng states; loads with
``weights_only=True``), ``history.csv``; all written atomically every epoch. The training
stage publishes ``best.pt`` with float16 weights (:func:`half_weights`) and no ``last.pt``.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from flowmod import dag
from flowmod.artefacts import atomic_path, read_manifest, save_checkpoint
from flowmod.crops import fold_crops, hflip
from flowmod.dag import StageParams
from flowmod.environment import resolve_device, torch_threads
from flowmod.metrics import metrics, sigmoid
from flowmod.params import Params
from flowmod.progress import bar as tqdm

if TYPE_CHECKING:  # torch is imported where a model is trained: the stage's declaration,
    # its parts and recipes (which every chapter and the runner read) never load it
    import torch
    from torch import nn

HISTORY_COLUMNS = [
    "epoch", "train_loss", "val_loss", "val_f1", "val_precision", "val_recall", "lr", "seconds",
]
CHECKPOINT_FORMAT = "flowmod-train-2"
#: Probabilities of the ``record`` crops after every epoch, (epochs, N) float32, never scored
#: during training (chapter 07 uses them to show what the original protocol would report).
EPOCH_PROBS = "epoch_probs.npy"
#: Torch threads a model trains on, on the CPU: one, so that its float reductions (and so its
#: weights) do not depend on the cores, and several models can train at once, one a core (two
#: 1-thread processes train 1.3-1.5x as fast as one on two threads:
#: ``benchmarks/bench_train_parallel.py``).
CPU_THREADS = 1
#: A trained classifier's published weights (float16 state_dict of its best validation epoch).
MODEL_FILE = "best.pt"
#: What a training node publishes: the weights, its history per epoch, and (for a seed the
#: original protocol replays) every epoch's probabilities on the test rows.
MODEL_OUTPUTS = (MODEL_FILE, "history.csv", EPOCH_PROBS)


def read_history(folder: Path) -> pd.DataFrame:
    """A published training node's history: one row per epoch (losses, validation F1,
    learning rate, seconds)."""
    return pd.read_csv(Path(folder) / "history.csv")


def model_file(folder: Path) -> Path:
    """The published weights of a ``train`` (or ``xtrain``, ``wtrain``, ``etrain``) node."""
    return Path(folder) / MODEL_FILE


class TrainingError(ValueError):
    """Training inputs are unusable (empty/single-class split, misaligned index) or a
    checkpoint does not match the run; the message says which and how to fix it."""


# --- inputs ----------------------------------------------------------------------------------


def _describe(x: Any, name: str) -> str:
    fn = getattr(x, "filename", None)
    return f"{name} crops ({fn})" if fn else f"{name} crops"


def check_split(
    x: Any, df: pd.DataFrame, name: str, label_col: str = "label", need_both: bool = False,
    channels: int = 2,
) -> np.ndarray:
    """Validate one split; return its labels (N,) float32 0/1.

    x: (N, C, S, S) crops (C = 2 for flow crops); df: the index with ``label_col``. Raises
    :class:`TrainingError` for a wrong shape, an index/array row mismatch, an empty split, labels other than 0/1, or
    (``need_both``) a split with only one class.
    """
    shape = tuple(getattr(x, "shape", ()))
    if len(shape) != 4 or shape[1] != channels or shape[2] != shape[3]:
        raise TrainingError(
            f"{_describe(x, name)}: expected (N, {channels}, S, S), got shape {shape}")
    if shape[0] != len(df):
        raise TrainingError(
            f"{name} split: index has {len(df)} rows but {_describe(x, name)} has {shape[0]} "
            "(the crop index and memmap disagree; rebuild the crops)"
        )
    if len(df) == 0:
        raise TrainingError(f"{name} split is empty: no objects to train/validate on")
    if label_col not in df.columns:
        raise TrainingError(f"{name} index has no {label_col!r} column (has {list(df.columns)})")
    y = df[label_col].to_numpy()
    if not np.isin(y, (0, 1)).all():
        raise TrainingError(f"{name} labels must be 0 (still) / 1 (moving), got {np.unique(y)}")
    if need_both and len(np.unique(y)) < 2:
        only = "moving" if y[0] == 1 else "still"
        raise TrainingError(
            f"{name} split has a single class (all {len(y)} objects {only}); a classifier "
            "cannot be trained on it: check the labels or the speed threshold"
        )
    return y.astype(np.float32)


class CropDataset:
    """Batches of crops: ``ds[indices] -> (x (B, C, S, S), y (B,) float32)``, x in the
    crops' stored dtype (float16 for memmaps: half the bytes to move; the training loop
    converts on the device).

    A memmap is re-opened by file name in DataLoader workers instead of being pickled whole.
    A map-style dataset as DataLoader reads one (``__len__``, ``__getitem__``), without
    ``torch.utils.data.Dataset`` as its base, so that defining it imports no torch.
    """

    def __init__(self, x: Any, y: np.ndarray) -> None:
        self.x = x
        self.y = np.asarray(y, dtype=np.float32)

    def __len__(self) -> int:
        return len(self.y)

    def __getitem__(self, idx: Sequence[int]) -> tuple[torch.Tensor, torch.Tensor]:
        import torch
        idx = np.asarray(idx)
        xb = torch.from_numpy(np.ascontiguousarray(self.x[idx]))
        return xb, torch.from_numpy(self.y[idx])

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        if isinstance(self.x, np.memmap) and self.x.filename:
            state["x"] = ("memmap", self.x.filename, self.x.dtype.str, self.x.shape,
                          self.x.offset)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        x = state["x"]
        if isinstance(x, tuple) and x and x[0] == "memmap":
            _, fn, dt, shape, offset = x
            state["x"] = np.memmap(fn, dtype=np.dtype(dt), mode="r", shape=shape, offset=offset)
        self.__dict__.update(state)


#: Training crops of at most this many bytes are copied to the device once and batched
#: there (the demo's: 13 MB a fold); larger ones stream from their memmap (DataLoader
#: workers, pinned memory on CUDA). On CUDA also at most a quarter of the free memory.
RESIDENT_BYTES = 2 * 1024**3


class ResidentCrops:
    """Training crops held whole on the device in their stored dtype: on CUDA a batch is an
    ``index_select`` and a float32 conversion there (no per-batch host work); on the CPU a
    numpy gather from memory (torch's float16 ``index_select`` on the CPU is ~50x slower)."""

    def __init__(self, x: Any, y: np.ndarray, dev: torch.device) -> None:
        import torch
        self.host = np.array(x)  # a copy in memory, off the memmap
        self.x = None if dev.type == "cpu" else torch.from_numpy(self.host).to(dev)
        self.y = torch.from_numpy(np.asarray(y, dtype=np.float32)).to(dev)
        self.dev = dev

    def __len__(self) -> int:
        return len(self.y)

    def batches(self, plan: Sequence[np.ndarray]) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        """(x (B, C, S, S) float32, y (B,)) on the device, per index array of ``plan``."""
        import torch
        for idx in plan:
            i = torch.from_numpy(np.asarray(idx, dtype=np.int64)).to(self.dev)
            if self.x is None:
                xb = torch.from_numpy(self.host[np.asarray(idx)])
            else:
                xb = self.x.index_select(0, i)  # pragma: no mutate (runs on CUDA only)
            yield xb.float(), self.y.index_select(0, i)


class StreamedCrops:
    """Training crops read per batch from their array (a memmap) on the host, through a
    DataLoader (``workers`` processes; pinned memory on CUDA), converted on the device."""

    def __init__(self, x: Any, y: np.ndarray, dev: torch.device, workers: int = 0) -> None:
        self.ds, self.dev, self.workers = CropDataset(x, y), dev, int(workers)

    def __len__(self) -> int:
        return len(self.ds)

    def host_batches(self, plan: Sequence[np.ndarray]
                     ) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        """The host's share: (x (B, C, S, S) as stored, y (B,)) per index array of ``plan``,
        pinned on CUDA."""
        from torch.utils.data import DataLoader
        yield from DataLoader(self.ds, batch_size=None, sampler=plan, num_workers=self.workers,
                              pin_memory=self.dev.type == "cuda")

    def batches(self, plan: Sequence[np.ndarray]) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        """(x (B, C, S, S) float32, y (B,)) on the device, per index array of ``plan``."""
        for xb, yb in self.host_batches(plan):
            yield (xb.to(self.dev, non_blocking=True).float(),
                   yb.to(self.dev, non_blocking=True))


def crop_source(x: Any, y: np.ndarray, dev: torch.device, workers: int = 0,
                resident_bytes: int = RESIDENT_BYTES) -> ResidentCrops | StreamedCrops:
    """Where training batches come from: the whole array (a numpy array or memmap) on the
    device when it fits (``resident_bytes``; on CUDA also a quarter of the free memory), else
    streamed (also any other array-like, such as chapter 10's inputs built per batch)."""
    import torch
    if not isinstance(x, np.ndarray):  # an array-like that assembles its crops per batch
        return StreamedCrops(x, y, dev, workers)
    nbytes = int(x.nbytes)
    limit = int(resident_bytes)
    if dev.type == "cuda":
        limit = min(limit, torch.cuda.mem_get_info(dev)[0] // 4)  # pragma: no mutate (CUDA)
    if nbytes <= limit:
        return ResidentCrops(x, y, dev)
    return StreamedCrops(x, y, dev, workers)


def epoch_plan(
    n: int, batch_size: int, hflip_p: float, seed: int, epoch: int
) -> tuple[list[np.ndarray], np.ndarray]:
    """Order and flips of one training epoch, a pure function of (seed, epoch).

    Returns (batches: list of sorted index arrays, flips: (n,) bool aligned with the
    concatenated batches). A trailing batch of one object is dropped (BatchNorm needs >= 2).
    """
    import torch
    g = torch.Generator().manual_seed(int(seed) * 1_000_003 + int(epoch))
    perm = torch.randperm(n, generator=g).numpy()
    flips = (torch.rand(n, generator=g) < hflip_p).numpy()
    batches = [np.sort(perm[a : a + batch_size]) for a in range(0, n, batch_size)]
    if len(batches) > 1 and len(batches[-1]) == 1:
        batches.pop()
        flips = flips[:-1]
    return batches, flips


# --- helpers ---------------------------------------------------------------------------------


@contextlib.contextmanager
def _deterministic(dev: torch.device) -> Iterator[None]:
    import torch
    prev = torch.are_deterministic_algorithms_enabled()
    prev_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    prev_bench = torch.backends.cudnn.benchmark
    if dev.type == "cuda":
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.use_deterministic_algorithms(True, warn_only=True)
    torch.backends.cudnn.benchmark = False
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(prev, warn_only=prev_warn)
        torch.backends.cudnn.benchmark = prev_bench


def _threads(dev: torch.device) -> contextlib.AbstractContextManager[None]:
    """Train on :data:`CPU_THREADS` threads on the CPU; on CUDA leave the count alone."""
    return torch_threads(CPU_THREADS) if dev.type == "cpu" else contextlib.nullcontext()


def _resolve_amp(amp: str | None, dev: torch.device) -> str | None:
    import torch
    if amp == "auto":
        if dev.type != "cuda":
            return None
        return "bf16" if torch.cuda.is_bf16_supported() else "fp16"
    if amp in (None, "none"):
        return None
    if amp not in ("bf16", "fp16"):
        raise ValueError(f"amp={amp!r}: use 'auto', None, 'bf16' or 'fp16'")
    return amp


def _bce_with_logits(z: np.ndarray, y: np.ndarray) -> float:
    """Mean binary cross-entropy of logits z against 0/1 labels y (numerically stable)."""
    z = z.astype(np.float64)
    return float(np.mean(np.maximum(z, 0) - z * y + np.log1p(np.exp(-np.abs(z)))))


def half_weights(path: Path) -> None:
    """Rewrite the state_dict at ``path`` with its floating-point tensors in float16 (integer
    buffers as they are); :func:`flowmod.model.load_model` loads it back into float32."""
    import torch
    state = torch.load(path, map_location="cpu", weights_only=True)
    save_checkpoint({k: v.half() if v.is_floating_point() else v for k, v in state.items()}, path)


def _append_probs(path: Path, epoch: int, probs: np.ndarray) -> None:
    """Store ``probs`` as row ``epoch - 1`` of the (epochs, N) array at ``path`` (atomic; rows
    of later epochs, left by a run that was resumed from an earlier checkpoint, dropped)."""
    old = np.load(path) if path.is_file() else np.zeros((0, len(probs)), np.float32)
    arr = np.concatenate([old[: epoch - 1], probs[None].astype(np.float32)])
    with atomic_path(path) as tmp:
        np.save(tmp, arr, allow_pickle=False)


def _history_dict(rows: list[dict[str, Any]]) -> dict[str, list[Any]]:
    return {c: [r[c] for r in rows] for c in HISTORY_COLUMNS}


def _history_rows(d: dict[str, list[Any]]) -> list[dict[str, Any]]:
    n = len(d["epoch"])
    return [{c: (int(d[c][i]) if c == "epoch" else float(d[c][i])) for c in HISTORY_COLUMNS}
            for i in range(n)]


def _history_frame(rows: list[dict[str, Any]], best_epoch: int, best_f1: float) -> pd.DataFrame:
    df = pd.DataFrame(rows, columns=HISTORY_COLUMNS)
    df.attrs.update(best_epoch=best_epoch, best_f1=best_f1)
    return df


# --- training --------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrainSettings:
    """The paper's Table 2 and how to run it (defaults: the paper's values)."""

    epochs: int = 60
    batch_size: int = 128
    lr: float = 0.01
    momentum: float = 0.9
    weight_decay: float = 0.01
    step_size: int = 10
    gamma: float = 0.5
    hflip_p: float = 0.5
    #: 'auto' (bf16/fp16 autocast on CUDA, off on CPU), None, 'bf16', 'fp16'
    amp: str | None = "auto"
    num_workers: int = 0
    device: str | torch.device = "auto"
    eval_batch_size: int = 256
    #: channels of the network's first stage (64: the paper's ResNet18)
    width: int = 64
    #: how the network scales the flow channels (:data:`flowmod.model.INPUT_MODES`)
    input_mode: str = "raw"
    #: training crops up to this size (bytes) are held on the device (:func:`crop_source`)
    resident_bytes: int = RESIDENT_BYTES

    @classmethod
    def of(cls, q: StageParams | Params) -> TrainSettings:
        """A training stage's settings from its parameters."""
        return cls(epochs=q.epochs, batch_size=q.batch_size, lr=q.lr, momentum=q.momentum,
                   weight_decay=q.weight_decay, step_size=q.step_size, gamma=q.gamma,
                   hflip_p=q.hflip_p, amp=None if q.amp == "off" else q.amp,
                   num_workers=q.num_workers, device=q.device, width=q.model_width,
                   input_mode=q.input_scaling)


@dataclass
class _Run:
    """What one training run holds: the model, its optimiser, schedule and scaler, the
    history so far and the best epoch."""

    model: nn.Module
    opt: torch.optim.Optimizer
    sched: Any
    scaler: Any
    rows: list[dict[str, Any]] = field(default_factory=list)
    best_f1: float = -1.0
    best_epoch: int = 0
    epoch: int = 0


def _new_run(s: TrainSettings, channels: int, seed: int, dev: torch.device,
             amp_mode: str | None, flow_channels: Sequence[int]) -> _Run:
    import torch

    from flowmod.model import motion_resnet18
    torch.manual_seed(seed)
    model = motion_resnet18(channels, s.width, s.input_mode, flow_channels)
    model = model.to(dev, memory_format=torch.channels_last)
    opt = torch.optim.SGD(model.parameters(), lr=s.lr, momentum=s.momentum,
                          weight_decay=s.weight_decay)
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=s.step_size, gamma=s.gamma)
    scaler = torch.amp.GradScaler(dev.type, enabled=amp_mode == "fp16")
    return _Run(model, opt, sched, scaler)


def _resume(run: _Run, last_path: Path, config: dict[str, Any], dev: torch.device) -> None:
    """Continue ``run`` from the checkpoint at ``last_path`` (made with ``config``)."""
    import torch
    ck = torch.load(last_path, map_location="cpu", weights_only=True)
    if ck.get("format") != CHECKPOINT_FORMAT:
        raise TrainingError(f"{last_path}: not a flowmod training checkpoint")
    diff = {k: (ck["config"].get(k), v) for k, v in config.items() if ck["config"].get(k) != v}
    if diff:
        raise TrainingError(
            f"{last_path} was written with other settings/data "
            f"(key: (checkpoint, now)) {diff}; pass resume=False or use a new out_dir"
        )
    run.model.load_state_dict(ck["model"])
    run.opt.load_state_dict(ck["optimizer"])
    run.sched.load_state_dict(ck["scheduler"])
    run.scaler.load_state_dict(ck["scaler"])
    run.rows = _history_rows(ck["history"])
    run.best_f1, run.best_epoch = float(ck["best_f1"]), int(ck["best_epoch"])
    run.epoch = int(ck["epoch"])
    torch.set_rng_state(ck["rng"]["torch"])
    if dev.type == "cuda" and ck["rng"].get("cuda"):
        torch.cuda.set_rng_state_all(ck["rng"]["cuda"])  # pragma: no mutate (CUDA only)


def _checkpoint(run: _Run, path: Path, config: dict[str, Any], dev: torch.device) -> None:
    import torch
    save_checkpoint({
        "format": CHECKPOINT_FORMAT, "epoch": run.epoch, "config": config,
        "model": run.model.state_dict(), "optimizer": run.opt.state_dict(),
        "scheduler": run.sched.state_dict(), "scaler": run.scaler.state_dict(),
        "history": _history_dict(run.rows), "best_f1": run.best_f1,
        "best_epoch": run.best_epoch,
        "rng": {"torch": torch.get_rng_state(),
                "cuda": torch.cuda.get_rng_state_all() if dev.type == "cuda" else []},
    }, path)


def _train_epoch(run: _Run, ds: ResidentCrops | StreamedCrops, s: TrainSettings, seed: int, epoch: int,
                 dev: torch.device, amp_dtype: Any, flip_negate: Sequence[int],
                 desc: str, progress: bool) -> float:
    """One epoch of SGD over ``ds`` in the order and with the flips of :func:`epoch_plan`;
    returns the mean training loss."""
    import torch
    from torch import nn
    batches, flips = epoch_plan(len(ds), s.batch_size, s.hflip_p, seed, epoch)
    run.model.train()
    loss_fn = nn.BCEWithLogitsLoss()
    loss_sum = torch.zeros((), dtype=torch.float64, device=dev)
    n_seen, pos = 0, 0
    inner = tqdm(ds.batches(batches), desc=f"{desc}, epoch {epoch}", unit="batch",
                 leave=False, disable=not progress, total=len(batches))
    for i, (xb, yb) in enumerate(inner):
        b = len(yb)
        fb = torch.from_numpy(flips[pos : pos + b]).to(dev)
        pos += b
        if bool(fb.any()):
            xb[fb] = hflip(xb[fb], flip_negate)
        xb = xb.contiguous(memory_format=torch.channels_last)
        run.opt.zero_grad(set_to_none=True)
        with torch.autocast(dev.type, dtype=amp_dtype, enabled=amp_dtype is not None):
            logits = run.model(xb).reshape(-1)
        loss = loss_fn(logits.float(), yb)
        if not torch.isfinite(loss):
            raise TrainingError(f"epoch {epoch}, batch {i}: loss is {loss.item()} (non-finite "
                                "crops? lr too high?)")
        run.scaler.scale(loss).backward()
        run.scaler.step(run.opt)
        run.scaler.update()
        loss_sum += loss.detach().double() * b
        n_seen += b
        if progress and i % 10 == 0:
            inner.set_postfix(loss=f"{loss.item():.4f}")
    inner.close()
    return float(loss_sum.item()) / max(1, n_seen)


def _config(s: TrainSettings, seed: int, amp_mode: str | None, train_x: Any, y_tr: np.ndarray,
            y_va: np.ndarray, channels: int, flip_negate: Sequence[int],
            flow_channels: Sequence[int] = (0, 1)) -> dict[str, Any]:
    """What a checkpoint must have been made with to be resumed."""
    config = {
        "batch_size": int(s.batch_size), "lr": float(s.lr), "momentum": float(s.momentum),
        "weight_decay": float(s.weight_decay), "step_size": int(s.step_size),
        "gamma": float(s.gamma), "hflip_p": float(s.hflip_p), "seed": int(seed),
        "amp": str(amp_mode), "crop_size": int(train_x.shape[2]),
        "n_train": len(y_tr), "n_train_moving": int(y_tr.sum()),
        "n_val": len(y_va), "n_val_moving": int(y_va.sum()),
    }
    if channels != 2 or tuple(flip_negate) != (0,):  # the paper's input keeps its old config
        config.update(channels=channels, flip_negate=[int(c) for c in flip_negate])
    if s.width != 64:  # as the paper's network's config
        config.update(width=int(s.width))
    if s.input_mode != "raw":  # as the paper's input's config
        config.update(input_mode=s.input_mode, flow_channels=[int(c) for c in flow_channels])
    return config


def _check_inputs(train_x: Any, train_df: pd.DataFrame, val_x: Any, val_df: pd.DataFrame,
                  s: TrainSettings, label_col: str, channels: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    y_tr = check_split(train_x, train_df, "train", label_col, need_both=True, channels=channels)
    y_va = check_split(val_x, val_df, "val", label_col, channels=channels)
    if train_x.shape[2] != val_x.shape[2]:
        raise TrainingError(
            f"crop sizes differ: train S={train_x.shape[2]}, val S={val_x.shape[2]}")
    if s.epochs < 1 or s.batch_size < 2:
        raise TrainingError(f"need epochs >= 1 and batch_size >= 2, got {s.epochs}, "
                            f"{s.batch_size}")
    return y_tr, y_va


def train_model(
    train_x: Any, train_df: pd.DataFrame, val_x: Any, val_df: pd.DataFrame,
    out_dir: str | os.PathLike[str], settings: TrainSettings | None = None, *,
    seed: int = 0, label_col: str = "label", resume: bool = True, progress: bool = True,
    record: Any | None = None, desc: str = "train", in_channels: int = 2,
    flip_negate: Sequence[int] = (0,), flow_channels: Sequence[int] = (0, 1),
    **overrides: Any,
) -> pd.DataFrame:
    """Train motion_resnet18 on crops; select the epoch with the best validation F1.

    train_x, val_x: (N, C, S, S) crops (float16 memmaps from :func:`flowmod.crops.read_crops`
    or any array-like with ``shape`` and ``x[indices]``), pixels; C = ``in_channels``: 2 (u,
    v) for the paper's input, others for chapter 10's inputs, whose horizontal flip negates
    the channels ``flip_negate`` (the horizontal flow components) and whose input scaling
    (``settings.input_mode``) applies to ``flow_channels``; train_df, val_df: their
    indices with ``label_col`` (1 moving, 0 still). ``settings``: Table 2
    (:class:`TrainSettings`; ``overrides`` replace single fields, e.g. ``epochs=2``). With
    ``resume`` and an ``out_dir/last.pt`` of the same settings, training continues after its
    last epoch (``epochs`` may be raised to train longer).

    ``record`` (crops, e.g. the test split): their probabilities after every epoch are saved
    to ``out_dir/epoch_probs.npy`` and never scored or looked at here, so that evaluation can
    show afterwards what choosing the epoch on the reported set (the original's protocol)
    would give; nothing of them influences training or selection.

    Returns the history (columns :data:`HISTORY_COLUMNS`; ``attrs`` best_epoch, best_f1),
    also written to ``out_dir/history.csv``. Weights: ``best.pt``, ``last.pt``.
    """
    import torch
    s = replace(settings or TrainSettings(), **overrides)
    channels = int(in_channels)
    y_tr, y_va = _check_inputs(train_x, train_df, val_x, val_df, s, label_col, channels)
    dev = resolve_device(s.device)
    amp_mode = _resolve_amp(s.amp, dev)
    amp_dtype = {"bf16": torch.bfloat16, "fp16": torch.float16, None: None}[amp_mode]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    config = _config(s, seed, amp_mode, train_x, y_tr, y_va, channels, flip_negate,
                     flow_channels)
    with _deterministic(dev), _threads(dev):
        run = _new_run(s, channels, seed, dev, amp_mode, flow_channels)
        if resume and (out / "last.pt").is_file():
            _resume(run, out / "last.pt", config, dev)
        ds = crop_source(train_x, y_tr, dev, s.num_workers, s.resident_bytes)
        bar = tqdm(range(run.epoch + 1, s.epochs + 1), desc=desc, unit="epoch",
                   disable=not progress, initial=run.epoch, total=s.epochs)
        for epoch in bar:
            t0 = time.perf_counter()
            lr_now = float(run.opt.param_groups[0]["lr"])
            train_loss = _train_epoch(run, ds, s, seed, epoch, dev, amp_dtype, flip_negate,
                                      desc, progress)
            _end_epoch(run, epoch, train_loss, lr_now, t0, val_x, y_va, record, out, s, dev,
                       amp_mode)
            _checkpoint(run, out / "last.pt", config, dev)
            with atomic_path(out / "history.csv") as tmp:
                pd.DataFrame(run.rows, columns=HISTORY_COLUMNS).to_csv(tmp, index=False)
            bar.set_postfix(loss=f"{train_loss:.4f}", val_f1=f"{run.rows[-1]['val_f1']:.3f}",
                            best=f"{run.best_epoch}")
        bar.close()
    if not math.isfinite(run.best_f1) or run.best_epoch == 0:
        raise TrainingError("no epoch was trained (epochs <= the checkpoint's epoch?)")
    return _history_frame(run.rows, run.best_epoch, run.best_f1)


def _end_epoch(run: _Run, epoch: int, train_loss: float, lr_now: float, t0: float,
               val_x: Any, y_va: np.ndarray, record: Any | None, out: Path, s: TrainSettings,
               dev: torch.device, amp_mode: str | None) -> None:
    """Validate, step the schedule, record the epoch (and ``record``'s probabilities) and
    keep the weights if the validation F1 is the best so far (ties keep the earlier)."""
    from flowmod.model import predict_logits
    z = predict_logits(run.model, val_x, batch_size=s.eval_batch_size, device=dev, amp=amp_mode)
    m = metrics(y_va, sigmoid(z))
    run.sched.step()
    run.rows.append({
        "epoch": epoch, "train_loss": train_loss, "val_loss": _bce_with_logits(z, y_va),
        "val_f1": m["f1"], "val_precision": m["precision"], "val_recall": m["recall"],
        "lr": lr_now, "seconds": time.perf_counter() - t0,
    })
    if record is not None:
        z_rec = predict_logits(run.model, record, batch_size=s.eval_batch_size, device=dev,
                               amp=amp_mode)
        _append_probs(out / EPOCH_PROBS, epoch, sigmoid(z_rec))
    if m["f1"] > run.best_f1:  # strict: ties keep the earlier epoch
        run.best_f1, run.best_epoch = m["f1"], epoch
        save_checkpoint(run.model.state_dict(), model_file(out))
    run.epoch = epoch


# --- the stages that train a seed (chapters 06, 10, 11) ---------------------------------------

def seed_parts(p: Params | StageParams, seeds: int | None = None) -> list[str]:
    """The parts of a training stage: with cross-validation one per fold (``f0`` ..
    ``f<folds-1>``) and, with several training seeds, one per fold and seed (``f<k>s<j>``);
    without, one per training seed (``s0`` .. ``s<seeds-1>``). ``seeds``: the training
    seeds (default ``p.seeds``, Table 3's; chapters 10 and 11 pass ``extension_seeds``)."""
    n = p.seeds if seeds is None else int(seeds)
    if p.folds > 1:
        if n == 1:
            return [f"f{k}" for k in range(p.folds)]
        return [f"f{k}s{j}" for k in range(p.folds) for j in range(n)]
    return [f"s{k}" for k in range(n)]


#: The prefix of a training part trained on the paper's raw input beside the profile's
#: recipe (``train[dis/raw/f0]``: ``raw_input_methods``).
RAW = "raw"


def raw_parts(p: Params | StageParams) -> list[str]:
    """The parts of a method's raw-input models (``raw/f<k>``, or ``raw/s0`` with one
    split): one seed a fold, seeded as seed 0 of the recipe's models, so that the pair
    differs in the input alone."""
    return [f"{RAW}/{k}" for k in seed_parts(p, 1)]


def is_raw(part: Any) -> bool:
    """Whether a training part is a raw-input model (:func:`raw_parts`)."""
    return str(part).startswith(f"{RAW}/")


def extension_parts(p: Params | StageParams) -> list[str]:
    """The training parts of the chains beyond the paper (chapters 10 and 11)."""
    return seed_parts(p, p.extension_seeds)


def _part_name(part: str) -> str:
    name = str(part).rsplit("/", 1)[-1]
    if not (len(name) > 1 and name[0] in "fs"):
        raise ValueError(f"{part!r} is not a training part (s<j>, f<k> or f<k>s<j>)")
    return name


def part_index(part: str) -> int:
    """k of a training part ``.../s<k>``, ``.../f<k>`` or ``.../f<k>s<j>``: with folds the
    fold it is tested on, else its seed index."""
    name = _part_name(part)
    return int(name[1:].split("s", 1)[0])


def part_seed(part: str) -> int:
    """j, the training seed index of a part (``s<j>``, ``f<k>s<j>``; 0 for ``f<k>``)."""
    name = _part_name(part)
    if name[0] == "s":
        return int(name[1:])
    return int(name[1:].split("s", 1)[1]) if "s" in name[1:] else 0


def part_seed_offset(part: str) -> int:
    """What a part adds to the profile's ``seed`` to seed its training: k for ``s<k>`` and
    ``f<k>`` (as before seeds per fold existed), ``k + 100 j`` for ``f<k>s<j>`` (folds are
    at most 10, so no two parts share a seed)."""
    return part_index(part) + 100 * part_seed(part) if _part_name(part)[0] == "f" \
        else part_index(part)


def seed_index(node: dag.Node) -> int:
    """k of a training node's last part (:func:`part_index`)."""
    return part_index(str(node.part))


def train_seed(b: dag.Build, train: tuple[Any, pd.DataFrame], val: tuple[Any, pd.DataFrame],
               progress: bool, what: str, record: Any | None = None, in_channels: int = 2,
               flip_negate: Sequence[int] = (0,), flow_channels: Sequence[int] = (0, 1),
               input_mode: str | None = None, width: int | None = None) -> dict[str, Any]:
    """Train the model of a training node (``b``: ``train``, ``xtrain`` or ``wtrain``) in its
    building folder, seed ``seed +`` :func:`part_seed_offset`, with the profile's Table 2
    settings (resumable); then
    keep what a published model needs: ``best.pt`` in float16 (no test decision changes, see
    the differences page), no ``last.pt`` (the resumable checkpoint, twice best.pt, is only
    needed while building). ``input_mode``: the flow scaling instead of the profile's
    ``input_scaling``; ``width``: the network's width instead of the profile's
    ``model_width``. Returns the manifest's training fields."""
    q = b.params
    seed = q.seed + part_seed_offset(str(b.node.part))
    s = TrainSettings.of(q)
    s = s if input_mode is None else replace(s, input_mode=input_mode)
    s = s if width is None else replace(s, width=width)
    work = b.start(fresh=q.force)
    h = train_model(*train, *val, work, s, seed=seed, record=record,
                    resume=True, progress=progress, desc=f"train {what} seed {seed}",
                    in_channels=in_channels, flip_negate=flip_negate,
                    flow_channels=flow_channels)
    half_weights(model_file(work))
    (work / "last.pt").unlink(missing_ok=True)
    return {"best_epoch": int(h.attrs["best_epoch"]), "best_f1": float(h.attrs["best_f1"]),
            "seed": seed, "amp": q.amp, "input_scaling": s.input_mode, "width": s.width}


def recipe(b: dag.Build, method: str, part: str = "keyframe") -> dict[str, Any]:
    """How a model's inputs are made, from the published flow and crops it was trained on:
    flow method, its parameters (as the flow node recorded them) and the crop geometry.
    Stored in the model's manifest, so that a model can be applied to new frames
    (``python -m flowmod.predict``) without the run that made it."""
    flow = read_manifest(b.other(dag.Node("flow", method, "keyframe")) / "manifest.json")
    crops = read_manifest(b.other(dag.Node("crops", method, part)) / "manifest.json")
    return recipe_from(method, flow or {}, crops or {})


def recipe_from(method: str, flow_rec: dict[str, Any], crops_rec: dict[str, Any]
                ) -> dict[str, Any]:
    """:func:`recipe` from the manifests of the flow and crops nodes a model was trained on."""
    return {"method": method, "flow_params": flow_rec.get("params", {}),
            "flow_dtype": flow_rec.get("dtype"), "store_scale": flow_rec.get("store_scale"),
            "crop_size": crops_rec.get("params", {}).get("crop_size"),
            "crop_scale": crops_rec.get("params", {}).get("crop_scale")}


def records_test(part: Any) -> bool:
    """Whether a training part records its test rows' probabilities after every epoch (for
    chapter 07's replay of the original protocol): every seed of one split (``s<j>``), seed
    0 of each fold (``f<k>``, ``f<k>s0``: the replay costs ~10 % of a demo model, and the
    protocol's gap is a mean over models); never a raw-input model."""
    name = _part_name(str(part))
    return not is_raw(part) and (name[0] == "s" or part_seed(name) == 0)


def build(b: dag.Build, progress: bool) -> dict[str, Any]:
    """Build one ``train[<method>/<part>]`` node: a classifier on the method's keyframe
    train/val crops of its split or fold; seed 0's records the test crops' probabilities
    every epoch (never scored); a ``raw/...`` part trains on the paper's raw input."""
    m, folds, k, part = b.node.method, b.params.folds, seed_index(b.node), b.node.part
    folder = b.input_dir(dag.Node("crops", m, "keyframe"))
    train, val, test = (fold_crops(folder, folds, k, role) for role in ("train", "val", "test"))
    info = train_seed(b, train, val, progress, f"{m}{' raw input' * is_raw(part)}",
                      record=test[0] if records_test(part) else None,
                      input_mode="raw" if is_raw(part) else None)
    return {**info, "recipe": recipe(b, m)}


def raw_nodes(p: Params, method: str) -> list[dag.Node]:
    """``method``'s raw-input models (:func:`raw_parts`) if ``raw_input_methods`` names it."""
    if method not in (p.raw_input_methods or []):
        return []
    return [dag.Node("train", method, k) for k in raw_parts(p)]


def train_nodes(p: Params) -> list[dag.Node]:
    """The training stage's nodes: every method's seeds of each fold, then the raw-input
    models of ``raw_input_methods``."""
    return ([dag.Node("train", m, k) for m in p.flow_methods for k in seed_parts(p)]
            + [n for m in p.flow_methods for n in raw_nodes(p, m)])


#: The training stage (chapter 06): the classifier of one training seed.
STAGE = dag.Stage("train", 4, "06", "models/{method}/{part}", "the classifier of one training seed",
                  nodes=train_nodes,
                  inputs=lambda n, p: (dag.Node("crops", n.method, "keyframe"),), build=build,
                  outputs=MODEL_OUTPUTS, parallel=True)
