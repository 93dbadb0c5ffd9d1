"""flowmod.model, flowmod.train, flowmod.evaluate: shapes, determinism, resume, metrics."""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from sklearn.metrics import accuracy_score, confusion_matrix, precision_recall_fscore_support

from flowmod import metrics as ev
from flowmod.model import (
    RESNET18_PARAMS,
    CheckpointError,
    count_parameters,
    load_model,
    motion_resnet18,
    predict,
    predict_logits,
)
from flowmod.train import HISTORY_COLUMNS, TrainingError, epoch_plan, train_model


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Keep CPU use modest; bit-identity holds for a fixed thread count (set before run_a)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# --- model ------------------------------------------------------------------------------------


def test_parameter_count_is_resnet18_minus_the_changes() -> None:
    conv1_removed = 64 * 1 * 7 * 7  # one input channel fewer (3 -> 2), no bias
    fc_removed = (512 * 1000 + 1000) - (512 * 1 + 1)  # 1000 -> 1 outputs
    expected = RESNET18_PARAMS - conv1_removed - fc_removed
    assert expected == 11_173_889
    assert count_parameters(motion_resnet18()) == expected


@pytest.mark.parametrize("size", [32, 64, 224])
def test_output_is_one_logit_per_crop(size: int) -> None:
    model = motion_resnet18().eval()
    with torch.inference_mode():
        out = model(torch.randn(2, 2, size, size))
    assert out.shape == (2, 1)


def test_load_model_refuses_another_architecture(tmp_path) -> None:
    from torchvision.models import resnet18

    path = tmp_path / "rgb_resnet18.pt"
    torch.save(resnet18(weights=None).state_dict(), path)
    with pytest.raises(CheckpointError) as e:
        load_model(path)
    msg = str(e.value)
    assert str(path) in msg and "conv1.weight" in msg and "fc.weight" in msg
    assert "(64, 3, 7, 7)" in msg and "(64, 2, 7, 7)" in msg
    torch.save({"head.weight": torch.zeros(3)}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="missing keys"):
        load_model(tmp_path / "other.pt")
    torch.save([1, 2], tmp_path / "list.pt")
    with pytest.raises(CheckpointError, match="not a state_dict"):
        load_model(tmp_path / "list.pt")


def test_a_loaded_model_holds_exactly_the_checkpoint_s_tensors(tmp_path) -> None:
    """load_model builds the network without initialising it (on the meta device) and takes
    every tensor from the file: nothing is left on meta, each parameter and buffer equals the
    saved one in float32 (a half-precision file too), and the outputs are the model's."""
    model = motion_resnet18(2, 8).eval()
    torch.save(model.state_dict(), tmp_path / "m.pt")
    torch.save({k: v.half() if v.is_floating_point() else v
                for k, v in model.state_dict().items()}, tmp_path / "half.pt")
    x = torch.randn(3, 2, 32, 32)
    for name, tol in (("m.pt", 0.0), ("half.pt", 1e-2)):
        loaded = load_model(tmp_path / name)
        tensors = list(loaded.state_dict().items())
        assert not any(t.is_meta for _, t in tensors) and not loaded.training
        assert {k: t.dtype for k, t in tensors} == {
            k: t.dtype for k, t in model.state_dict().items()}
        assert all(torch.allclose(t, model.state_dict()[k].to(t.dtype), atol=tol, rtol=tol)
                   for k, t in tensors)
        with torch.inference_mode():
            assert torch.allclose(loaded(x), model(x), atol=tol * 10, rtol=tol * 10)
    assert torch.equal(load_model(tmp_path / "m.pt").conv1.weight, model.conv1.weight)


def test_input_scalings_of_the_flow_channels() -> None:
    from flowmod.model import CLIP_PX, scale_input

    rng = np.random.default_rng(1)
    x = torch.from_numpy(rng.normal(40, 30, (3, 4, 8, 8)).astype(np.float32))
    before = x.clone()
    c = scale_input(x, "centred", (0, 1))
    assert torch.equal(x, before)  # a new tensor
    assert torch.equal(c[:, 2:], x[:, 2:])  # the other channels as they are
    med = x[:, :2].flatten(2).median(dim=2).values
    assert torch.allclose(c[:, :2], x[:, :2] - med[..., None, None])
    assert scale_input(x, "clipped")[:, :2].abs().max() == CLIP_PX < x[:, :2].abs().max()
    assert torch.allclose(scale_input(x, "log")[:, 0], torch.sign(x[:, 0]) * torch.log1p(x[:, 0].abs()))
    assert torch.allclose(scale_input(x, "centred-log")[:, :2],
                          scale_input(c, "log")[:, :2], atol=1e-6)
    assert scale_input(x, "raw") is x
    with pytest.raises(ValueError, match="input mode 'median'"):
        scale_input(x, "median")


def test_a_centred_network_ignores_each_crop_s_common_flow(tmp_path) -> None:
    """The network scales its own input, and its weights carry how: a loaded model of a
    centred run answers the same to a crop and to the crop plus any constant flow."""
    from flowmod.model import input_mode_of

    torch.manual_seed(0)
    model = motion_resnet18(2, 8, "centred").eval()
    path = tmp_path / "centred.pt"
    torch.save(model.state_dict(), path)
    loaded = load_model(path)
    assert input_mode_of(loaded) == "centred" and input_mode_of(motion_resnet18(2, 8)) == "raw"
    x = torch.randn(4, 2, 32, 32)
    shift = torch.tensor([120.0, -35.0])[None, :, None, None] * torch.arange(1, 5.0)[:, None,
                                                                                      None, None]
    with torch.inference_mode():
        assert torch.allclose(loaded(x), loaded(x + shift), atol=1e-4)
        assert torch.allclose(loaded(x), model(x))
        raw = motion_resnet18(2, 8).eval()
        raw.load_state_dict({k: v for k, v in model.state_dict().items()
                             if not k.startswith("input_")})
        assert not torch.allclose(raw(x), raw(x + shift), atol=1e-2)
    assert not any(k.startswith("input_") for k in motion_resnet18().state_dict())  # paper's
    bad = dict(model.state_dict(), input_mode=torch.tensor(17))
    torch.save(bad, tmp_path / "bad.pt")
    with pytest.raises(CheckpointError, match="known input scalings"):
        load_model(tmp_path / "bad.pt")


# --- training ---------------------------------------------------------------------------------

N, S = 64, 32
#: width 16: the training mechanics are width-blind, and a quarter of the paper's width
#: trains about 15x faster (the mutation run repeats these tests for every mutant)
KW = dict(epochs=2, batch_size=16, progress=False, seed=3, device="cpu", width=16)


@pytest.fixture(scope="module")
def data() -> tuple[np.ndarray, pd.DataFrame, np.ndarray, pd.DataFrame]:
    """64 train + 32 val crops; moving ones carry a uniform rightward flow on the object."""
    rng = np.random.default_rng(0)

    def make(n: int) -> tuple[np.ndarray, pd.DataFrame]:
        y = np.arange(n) % 2
        rng.shuffle(y)
        x = rng.normal(0, 0.3, (n, 2, S, S)).astype(np.float32)
        x[y == 1, 0, 10:22, 10:22] += 3.0
        return x.astype(np.float16), pd.DataFrame({"label": y, "category": "vehicle.car"})

    return (*make(N), *make(32))


@pytest.fixture(scope="module")
def run_a(_one_thread, data, tmp_path_factory):
    out = tmp_path_factory.mktemp("run_a")
    tx, tdf, vx, vdf = data
    before = tx.copy()
    hist = train_model(tx, tdf, vx, vdf, out, **KW)
    np.testing.assert_array_equal(tx, before)  # training never writes into its inputs
    return out, hist


def _state(path) -> dict[str, torch.Tensor]:
    obj = torch.load(path, map_location="cpu", weights_only=True)
    return obj["model"] if "model" in obj else obj


def _assert_same_weights(a, b) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_training_lowers_the_loss_and_writes_artefacts(data, run_a) -> None:
    tx, tdf, vx, vdf = data
    out, hist = run_a
    torch.manual_seed(KW["seed"])  # the initial model of the run
    z0 = predict_logits(motion_resnet18(width=KW["width"]), vx, device="cpu")
    y = vdf["label"].to_numpy()
    loss0 = float(np.mean(np.maximum(z0, 0) - z0 * y + np.log1p(np.exp(-np.abs(z0)))))
    assert list(hist.columns) == HISTORY_COLUMNS and list(hist["epoch"]) == [1, 2]
    assert hist["val_loss"].iloc[0] < loss0
    assert hist["val_f1"].max() > 0.9  # separable: learnt within two epochs
    assert hist["lr"].tolist() == [0.01, 0.01]
    for name in ("best.pt", "last.pt", "history.csv"):
        assert (out / name).is_file()
    pd.testing.assert_frame_equal(pd.read_csv(out / "history.csv"), hist, check_dtype=False)
    # model selection on val: best.pt is the epoch with the highest val F1 (ties -> earlier)
    best = int(hist["val_f1"].to_numpy().argmax()) + 1
    assert hist.attrs["best_epoch"] == best
    loaded = load_model(out / "best.pt")  # state_dict only, loads with weights_only
    assert isinstance(loaded, torch.nn.Module)
    if best == 2:
        _assert_same_weights(_state(out / "best.pt"), _state(out / "last.pt"))


def test_same_seed_is_bit_identical(data, run_a, tmp_path) -> None:
    tx, tdf, vx, vdf = data
    out_a, hist_a = run_a
    hist_b = train_model(tx, tdf, vx, vdf, tmp_path, **KW)
    cols = [c for c in HISTORY_COLUMNS if c != "seconds"]
    pd.testing.assert_frame_equal(hist_a[cols], hist_b[cols], check_exact=True)
    _assert_same_weights(_state(out_a / "last.pt"), _state(tmp_path / "last.pt"))
    # and the published weights byte for byte (last.pt records the seconds each epoch took)
    assert (out_a / "best.pt").read_bytes() == (tmp_path / "best.pt").read_bytes()


def test_on_the_cpu_a_model_trains_on_one_thread_whatever_the_caller_s_count(
        data, run_a, tmp_path, monkeypatch) -> None:
    """Training runs on CPU_THREADS (1) torch thread and gives the caller its count back, so
    a process on two threads trains the same bytes as one on one thread (and as a worker of
    a parallel build)."""
    import flowmod.train as tr

    assert tr.CPU_THREADS == 1
    tx, tdf, vx, vdf = data
    seen: list[int] = []
    build = motion_resnet18

    def hooked(*a, **k):
        model = build(*a, **k)
        model.register_forward_pre_hook(lambda m, i: seen.append(torch.get_num_threads()))
        return model

    monkeypatch.setattr("flowmod.model.motion_resnet18", hooked)
    torch.set_num_threads(2)
    try:
        train_model(tx, tdf, vx, vdf, tmp_path, **KW)
        after = torch.get_num_threads()
    finally:
        torch.set_num_threads(1)
    assert after == 2, "the caller's thread count is restored"
    assert seen and set(seen) == {1}
    assert (run_a[0] / "best.pt").read_bytes() == (tmp_path / "best.pt").read_bytes()


def test_equal_tensors_save_to_equal_bytes(tmp_path) -> None:
    """``save_checkpoint``, the package's one writer of .pt files: the same state_dict
    saved twice (under other names, in other folders) gives the same bytes, and loads with
    ``weights_only`` (torch.save to a path names the zip's folder after the temporary file)."""
    from flowmod.artefacts import save_checkpoint

    def state() -> dict[str, torch.Tensor]:  # a new model each call, equal weights
        torch.manual_seed(0)
        return motion_resnet18(width=8).state_dict()

    a, b = tmp_path / "a" / "best.pt", tmp_path / "b" / "other.pt"
    save_checkpoint(state(), a)
    save_checkpoint(state(), b)
    assert a.read_bytes() == b.read_bytes()
    _assert_same_weights(torch.load(b, map_location="cpu", weights_only=True), state())
    assert sorted(p.name for p in b.parent.iterdir()) == ["other.pt"], "no temporary file left"


def test_resume_gives_the_uninterrupted_result(data, run_a, tmp_path) -> None:
    tx, tdf, vx, vdf = data
    out_a, hist_a = run_a
    first = train_model(tx, tdf, vx, vdf, tmp_path, **{**KW, "epochs": 1})
    assert len(first) == 1
    resumed = train_model(tx, tdf, vx, vdf, tmp_path, **KW)
    cols = [c for c in HISTORY_COLUMNS if c != "seconds"]
    pd.testing.assert_frame_equal(hist_a[cols], resumed[cols], check_exact=True)
    _assert_same_weights(_state(out_a / "last.pt"), _state(tmp_path / "last.pt"))
    _assert_same_weights(_state(out_a / "best.pt"), _state(tmp_path / "best.pt"))
    with pytest.raises(TrainingError, match=r"other settings.*'lr': \(0.01, 0.1\)"):
        train_model(tx, tdf, vx, vdf, tmp_path, **{**KW, "lr": 0.1})


def test_the_recorded_rate_falls_by_gamma_at_each_step_and_resumes_on_schedule(data,
                                                                               tmp_path) -> None:
    """The history's ``lr`` is the rate each epoch trained at: StepLR multiplies it by gamma
    every ``step_size`` epochs (issue 53: a scheduler never stepped trained every model at
    its first rate while the tests looked only at the scheduler object). Stopped after epoch
    3 and resumed, the schedule goes on where it was, not from the start."""
    tx, tdf, vx, vdf = data
    kw = {**KW, "epochs": 5, "lr": 0.02, "step_size": 2, "gamma": 0.3}
    small = (tx[:16], tdf.iloc[:16], vx[:8], vdf.iloc[:8])  # the rate, not the fit, is tested
    assert small[1]["label"].nunique() == small[3]["label"].nunique() == 2
    assert len(train_model(*small, tmp_path, **{**kw, "epochs": 3})) == 3
    hist = train_model(*small, tmp_path, **kw)
    assert hist["epoch"].tolist() == [1, 2, 3, 4, 5]
    assert hist["lr"].tolist() == pytest.approx([0.02, 0.02, 0.006, 0.006, 0.0018], rel=1e-12)


def test_epoch_plan_is_a_function_of_seed_and_epoch() -> None:
    b1, f1 = epoch_plan(33, 8, 0.5, seed=1, epoch=4)
    b2, f2 = epoch_plan(33, 8, 0.5, seed=1, epoch=4)
    b3, _ = epoch_plan(33, 8, 0.5, seed=1, epoch=5)
    assert all(np.array_equal(a, b) for a, b in zip(b1, b2, strict=True))
    assert np.array_equal(f1, f2)
    assert not all(np.array_equal(a, b) for a, b in zip(b1, b3, strict=False))
    kept = np.concatenate(b1)  # a trailing batch of one is dropped
    assert len(kept) == 32 and len(np.unique(kept)) == 32
    assert len(f1) == 32 and not epoch_plan(10, 4, 0.0, 0, 1)[1].any()


def test_bad_training_inputs_give_clear_errors(data, tmp_path) -> None:
    tx, tdf, vx, vdf = data
    with pytest.raises(TrainingError, match="empty"):
        train_model(tx[:0], tdf.iloc[:0], vx, vdf, tmp_path, **KW)
    with pytest.raises(TrainingError, match="single class"):
        train_model(tx, tdf.assign(label=0), vx, vdf, tmp_path, **KW)
    with pytest.raises(TrainingError, match="index has 63 rows .* has 64"):
        train_model(tx, tdf.iloc[:-1], vx, vdf, tmp_path, **KW)
    with pytest.raises(TrainingError, match=r"\(N, 2, S, S\)"):
        train_model(tx[:, :1], tdf, vx, vdf, tmp_path, **KW)
    with pytest.raises(TrainingError, match=r"^val split is empty"):
        train_model(tx, tdf, vx[:0], vdf.iloc[:0], tmp_path, **KW)
    with pytest.raises(TrainingError, match=r"^train split has a single class \(all 64 objects "
                                            r"moving\); a classifier cannot be trained on it: "
                                            r"check the labels or the speed threshold$"):
        train_model(tx, tdf.assign(label=1), vx, vdf, tmp_path, **KW)
    with pytest.raises(TrainingError, match=r"^train split has a single class \(all 64 objects "
                                            r"still\)"):
        train_model(tx, tdf.assign(label=0), vx, vdf, tmp_path, **KW)
    with pytest.raises(TrainingError, match=r"^val index has no 'label' column \(has "
                                            r"\['moving', 'category'\]\)$"):
        train_model(tx, tdf, vx, vdf.rename(columns={"label": "moving"}), tmp_path, **KW)
    with pytest.raises(TrainingError, match=r"^train labels must be 0 \(still\) / 1 \(moving\), "
                                            r"got \[0 1 2\]$"):
        train_model(tx, tdf.assign(label=np.arange(64) % 3), vx, vdf, tmp_path, **KW)
    with pytest.raises(TrainingError, match=r"^crop sizes differ: train S=32, val S=16$"):
        train_model(tx, tdf, vx[:, :, :16, :16], vdf, tmp_path, **KW)
    with pytest.raises(TrainingError, match=r"^val crops: expected \(N, 2, S, S\), got shape "
                                            r"\(32, 2, 32, 16\)$"):
        train_model(tx, tdf, vx[:, :, :, :16], vdf, tmp_path, **KW)
    for bad_settings, got in (({"epochs": 0}, "0, 16"), ({"batch_size": 1}, "2, 1")):
        with pytest.raises(TrainingError, match=rf"^need epochs >= 1 and batch_size >= 2, got "
                                                rf"{got}$"):
            train_model(tx, tdf, vx, vdf, tmp_path, **{**KW, **bad_settings})
    # another label column, and the smallest batch
    renamed = [d.rename(columns={"label": "moving"}) for d in (tdf, vdf)]
    assert len(train_model(tx, renamed[0], vx, renamed[1], tmp_path / "col", label_col="moving",
                           **{**KW, "epochs": 1})) == 1
    assert tdf["label"].iloc[:8].nunique() == 2
    assert len(train_model(tx[:8], tdf.iloc[:8], vx, vdf, tmp_path / "b2",
                           **{**KW, "epochs": 1, "batch_size": 2})) == 1
    with pytest.raises(TrainingError, match="empty"):
        train_model(tx, tdf, vx[:0], vdf.iloc[:0], tmp_path, **KW)
    assert not (tmp_path / "last.pt").exists()
    bad = tx.copy()
    bad[:, 0, 0, 0] = np.inf
    with pytest.raises(TrainingError, match=r"epoch 1, batch 0: loss is nan \(non-finite "
                                            r"crops\? lr too high\?\)"):
        train_model(bad, tdf, vx, vdf, tmp_path / "inf", **{**KW, "epochs": 1})


def test_check_split_names_the_crops_file_and_returns_float32_labels(tmp_path) -> None:
    """An input without a shape is one clear error; a row mismatch names the crops' file;
    the labels come back as float32 0/1."""
    from flowmod.train import check_split

    np.save(tmp_path / "x.npy", np.zeros((3, 2, 4, 4), np.float16))
    x = np.load(tmp_path / "x.npy", mmap_mode="r")
    df = pd.DataFrame({"label": [1, 0, 1]})
    y = check_split(x, df, "train")
    assert y.dtype == np.float32 and y.tolist() == [1.0, 0.0, 1.0]
    with pytest.raises(TrainingError, match=r"train crops: expected \(N, 2, S, S\), got "
                                            r"shape \(\)"):
        check_split([[1.0]], df, "train")
    with pytest.raises(TrainingError, match=r"val split: index has 2 rows but val crops "
                                            r"\(.*x\.npy\) has 3 \(the crop index and memmap "
                                            r"disagree; rebuild the crops\)$"):
        check_split(x, df.iloc[:2], "val")
    assert check_split(x, df.assign(label=1), "val").tolist() == [1.0] * 3  # one class: fine
    np.save(tmp_path / "odd.npy", np.zeros((3, 2, 4, 5), np.float16))
    with pytest.raises(TrainingError, match=r"^train crops \(.*odd\.npy\): expected \(N, 2, "
                                            r"S, S\), got shape \(3, 2, 4, 5\)$"):
        check_split(np.load(tmp_path / "odd.npy", mmap_mode="r"), df, "train")


def test_a_dataset_of_an_in_memory_array_pickles_whole() -> None:
    """Only a memmap travels to DataLoader workers as its file name; an array in memory
    is pickled with the dataset and comes back equal."""
    import pickle

    from flowmod.train import CropDataset

    x = np.arange(2 * 2 * 4 * 4, dtype=np.float16).reshape(2, 2, 4, 4)
    back = pickle.loads(pickle.dumps(CropDataset(x, np.array([0, 1]))))
    xb, yb = back[[1, 0]]
    np.testing.assert_array_equal(xb.numpy(), x[[1, 0]])
    assert yb.tolist() == [1.0, 0.0]
    assert isinstance(back.x, np.ndarray) and not isinstance(back.x, np.memmap)


def test_epoch_plan_drops_only_a_trailing_batch_of_one() -> None:
    """Whole batches are all kept; a lone single object is kept (no other batch); a batch
    of one after others is dropped with its flip."""
    b, f = epoch_plan(32, 8, 0.5, seed=0, epoch=1)
    assert [len(x) for x in b] == [8, 8, 8, 8] and len(f) == 32
    b, f = epoch_plan(1, 8, 0.5, seed=0, epoch=1)
    assert [len(x) for x in b] == [1] and len(f) == 1
    b, f = epoch_plan(9, 8, 0.5, seed=0, epoch=1)
    assert [len(x) for x in b] == [8] and len(f) == 8


def test_recorded_probabilities_of_a_resumed_run_replace_later_rows(tmp_path) -> None:
    """Epoch e's probabilities are row e - 1; rows of later epochs (left by a run resumed
    from an earlier checkpoint) are dropped; stored as float32."""
    from flowmod.train import _append_probs

    path = tmp_path / "probs.npy"
    for e in (1, 2, 3):
        _append_probs(path, e, np.full(4, e / 10))
    _append_probs(path, 2, np.full(4, 0.9))
    arr = np.load(path)
    assert arr.dtype == np.float32 and arr.shape == (2, 4)
    np.testing.assert_allclose(arr[:, 0], [0.1, 0.9], rtol=1e-6)


def test_training_on_the_cpu_runs_in_float32_and_shows_its_progress(data, tmp_path, capsys,
                                                                    monkeypatch) -> None:
    """Without mixed precision the forward pass is float32 (autocast off on the CPU); with
    ``progress`` the epoch bar shows the loss, the validation F1 and the best epoch."""

    seen: list[torch.dtype] = []
    build = motion_resnet18

    def hooked(*a, **k):
        model = build(*a, **k)
        model.conv1.register_forward_hook(lambda m, i, o: seen.append(o.dtype))
        return model

    monkeypatch.setattr("flowmod.model.motion_resnet18", hooked)
    tx, tdf, vx, vdf = data
    kw = {**KW, "epochs": 1}
    del kw["progress"]  # shown by default
    train_model(tx, tdf, vx, vdf, tmp_path, **kw)
    assert seen and set(seen) == {torch.float32}
    err = capsys.readouterr().err
    assert re.search(r"best=1, loss=\d\.\d{4}, val_f1=\d\.\d{3}\]", err), err[-300:]
    assert re.search(r"train: 100%\|[^|]*\| 1/1 \[[^]]*epoch/s, best=1", err), err[-600:]
    # and the epoch's own bar: its batches, counted against their number, with the loss
    assert re.search(r"train, epoch 1: +\d+%\|[^|]*\| \d/4 \[[^]]*batch/s, loss=\d\.\d{4}\]",
                     err), err[-600:]


# --- evaluation -------------------------------------------------------------------------------

Y = np.array([1, 1, 0, 0, 1, 0, 1, 0, 0, 1, 1, 0])
P = np.array([0.9, 0.4, 0.2, 0.7, 0.8, 0.1, 0.51, 0.5, 0.3, 0.2, 0.95, 0.6])


def test_metrics_equal_sklearn() -> None:
    m = ev.metrics(Y, P)
    pred = (P > 0.5).astype(int)
    prec, rec, f1, _ = precision_recall_fscore_support(Y, pred, average="binary")
    assert (m["precision"], m["recall"], m["f1"]) == pytest.approx((prec, rec, f1), abs=1e-12)
    assert m["accuracy"] == pytest.approx(accuracy_score(Y, pred))
    assert m["confusion"] == confusion_matrix(Y, pred).tolist()
    assert (m["n"], m["n_moving"], m["n_still"]) == (12, 6, 6)
    none = ev.metrics([0, 0, 1], [0.1, 0.2, 0.3])  # nothing predicted moving
    assert np.isnan(none["precision"]), "undefined (sklearn warns and reports 0)"
    assert none["recall"] == none["f1"] == 0.0, "a missed mover: defined, 0"
    sweep = ev.threshold_sweep(Y, P, [0.3, 0.5])
    assert sweep.loc[1, "f1"] == pytest.approx(f1)
    curve, ap = ev.pr_curve(Y, P)
    assert 0 < ap <= 1 and curve["recall"].is_monotonic_increasing


def test_paper_protocol_differs_from_whole_set_f1() -> None:
    y = np.array([1, 1, 0, 0])
    p = np.array([0.9, 0.9, 0.9, 0.1])  # batch 1: F1 = 1; batch 2: no positives -> F1 = 0
    assert ev.metrics(y, p)["f1"] == pytest.approx(0.8)
    assert ev.paper_protocol_f1(y, p, batch_size=2) == pytest.approx(0.5)
    # the per-batch average equals an explicit sklearn loop over consecutive batches
    per_batch = [precision_recall_fscore_support(Y[a:a + 5], (P[a:a + 5] > 0.5).astype(int),
                                                 average="binary", zero_division=0)[2]
                 for a in range(0, len(Y), 5)]
    assert ev.paper_protocol_f1(Y, P, batch_size=5) == pytest.approx(np.mean(per_batch))
    table = ev.protocol_comparison(Y, P, batch_size=5)
    assert table["f1"].iloc[0] == pytest.approx(ev.metrics(Y, P)["f1"])
    assert len(table) == 4


def _original_thinning(y: np.ndarray, frac: tuple[int, int]) -> np.ndarray:
    """The original dataset's still-object counter, transcribed as a loop."""
    keep, count = [], 0
    for label in y:
        if label == 0:
            count += 1
            if frac[0] < count < frac[1]:
                keep.append(False)
                continue
            if count == frac[1]:
                count = 0
                keep.append(False)
                continue
        keep.append(True)
    return np.array(keep)


def test_thin_still_matches_the_original_counter() -> None:
    y = np.random.default_rng(0).integers(0, 2, 200)
    np.testing.assert_array_equal(ev.thin_still(y, 1, 2), _original_thinning(y, (1, 2)))
    np.testing.assert_array_equal(ev.thin_still(y, 3, 5), _original_thinning(y, (3, 5)))


def test_scene_bootstrap_resamples_whole_scenes() -> None:
    # one scene: every replicate is that scene, the interval is the point itself
    lo, hi = ev.bootstrap_f1_ci(Y, P, np.zeros(12), n=200, seed=1)
    assert lo == hi == pytest.approx(ev.metrics(Y, P)["f1"])
    # two scenes, A all right, B all wrong: replicates draw AA, AB/BA, BB with 1/4, 1/2, 1/4
    y = np.array([1, 1, 0, 1, 0, 0])
    p = np.array([0.9, 0.9, 0.1, 0.1, 0.9, 0.9])
    g = np.array(["A", "A", "A", "B", "B", "B"])
    f_aa = 1.0  # tp 4, fp 0, fn 0
    f_ab = ev.metrics(y, p)["f1"]  # tp 2, fp 2, fn 1: 4 / 7
    f_bb = 0.0
    reps = ev.scene_bootstrap(y, p, g, n=4000, seed=0)
    for value, share in ((f_aa, 0.25), (f_ab, 0.5), (f_bb, 0.25)):
        assert np.mean(np.isclose(reps, value)) == pytest.approx(share, abs=0.03)
    assert set(np.round(reps, 9)) == {round(f_aa, 9), round(f_ab, 9), round(f_bb, 9)}
    # resampling objects one by one (ignoring the scenes) would be much narrower (over
    # the replicates that drew a mover)
    objects = ev.scene_bootstrap(y, p, np.arange(6), n=4000, seed=0)
    assert np.isnan(objects).any() and not np.isnan(reps).any()
    width = [hi - lo for lo, hi in (ev.interval(reps), ev.interval(objects))]
    assert width[0] > width[1]
    assert (ev.bootstrap_f1_ci(y, p, g, n=300, seed=1)
            == ev.bootstrap_f1_ci(y, p, g, n=300, seed=1)), "seeded"


def test_seed_summary_and_paired_comparison() -> None:
    y = np.array([1, 1, 0, 0, 1, 0, 1, 0])
    good = np.where(y == 1, 0.9, 0.1)
    half = np.array([0.9, 0.1, 0.1, 0.9, 0.9, 0.1, 0.1, 0.1])  # tp 2, fp 1, fn 2
    scenes = np.array(["s1"] * 4 + ["s2"] * 4)
    s = ev.seed_summary(y, np.stack([good, half]), scenes, instances=["a", "a", "b", "c"] * 2)
    f_half = 2 * 2 / (2 * 2 + 1 + 2)
    assert s["seeds"] == 2 and s["f1_max"] == 1.0 and s["f1_min"] == pytest.approx(f_half)
    assert s["f1"] == pytest.approx((1 + f_half) / 2)
    assert (s["n"], s["n_scenes"], s["n_instances"], s["n_moving"]) == (8, 2, 3, 4)
    assert s["ci"][0] <= s["f1"] <= s["ci"][1]
    same = ev.paired_comparison(y, good, good, scenes)
    assert same["delta_f1"] == 0.0 and same["ci"] == (0.0, 0.0) and same["p_not_better"] == 1
    d = ev.paired_comparison(y, good, half, scenes, n=500)
    assert d["delta_f1"] == pytest.approx(1 - f_half) and d["per_seed"] == [
        pytest.approx(1 - f_half)]
    assert 0 < d["ci"][0] <= d["ci"][1] and d["p_not_better"] == 0.0
    t3 = ev.table3([{"method": "two seeds", **s}])
    assert t3.loc[0, "F1 (%)"] == round(100 * s["f1"], 1)
    assert t3.loc[0, "seed range (%)"] == f"{100 * f_half:.1f}-100.0"
    assert (t3.loc[0, "scenes"], t3.loc[0, "objects"], t3.loc[0, "vehicles"]) == (2, 8, 3)
    cmp = ev.comparison_table({"good - half": d})
    assert cmp.loc[0, "ΔF1 (points)"] == round(100 * (1 - f_half), 1)


def test_breakdown() -> None:
    df = pd.DataFrame({"category": ["car", "truck"] * 6, "distance": np.linspace(30, 69, 12)})
    by_cat = ev.breakdown(df, Y, P, by="category")
    assert by_cat["n"].sum() == 12 and set(by_cat["category"]) == {"car", "truck"}
    car = by_cat.set_index("category").loc["car"]
    assert car["f1"] == pytest.approx(ev.metrics(Y[::2], P[::2])["f1"])
    by_dist = ev.breakdown(df, Y, P, by="distance")
    assert by_dist["n"].sum() == 12 and "distance_bin" in by_dist


def test_fit_threshold_maximises_train_f1() -> None:
    rng = np.random.default_rng(2)
    y = rng.integers(0, 2, 300)
    s = rng.normal(0, 1, 300) + 1.5 * y
    t = ev.fit_threshold(s, y)
    best = max(ev.metrics(y, (s > c).astype(float))["f1"] for c in np.r_[s, s.min() - 1])
    assert ev.metrics(y, ev.apply_threshold(s, t).astype(float))["f1"] == pytest.approx(best)
    assert ev.fit_threshold([0.1, 0.2, 3.0, 4.0], [0, 0, 1, 1]) == pytest.approx(1.6)
    with pytest.raises(ValueError):
        ev.fit_threshold([], [])


def test_flips_are_used_in_training_only(data, run_a, tmp_path) -> None:
    tx, tdf, vx, vdf = data
    no_flip = train_model(tx, tdf, vx, vdf, tmp_path, **{**KW, "epochs": 1, "hflip_p": 0.0})
    assert no_flip["train_loss"].iloc[0] != run_a[1]["train_loss"].iloc[0]
    model = load_model(run_a[0] / "best.pt")
    with torch.inference_mode():  # evaluation: plain forward pass, no flips
        direct = torch.sigmoid(model(torch.from_numpy(vx.astype(np.float32)))).numpy().ravel()
    np.testing.assert_allclose(predict(model, vx, batch_size=7, device="cpu"), direct,
                               rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("channels, negate", [(2, (0,)), (3, (0, 2))])
def test_training_batches_are_flipped_with_u_negated(data, tmp_path, monkeypatch, channels,
                                                     negate) -> None:
    """Inside the training loop: each batch the model sees is the plan's crops, and exactly
    the planned ones mirrored with u negated (the original flipped without negating u); an
    input of other channels negates the channels it names (chapter 10)."""

    tx, tdf, vx, vdf = data
    if channels == 3:
        tx = np.concatenate([tx, tx[:, :1] * 0.5], axis=1)
        vx = np.concatenate([vx, vx[:, :1] * 0.5], axis=1)
    seen: list[torch.Tensor] = []

    def recording_model(in_channels=2, width=64, *scaling):
        model = motion_resnet18(in_channels, width, *scaling)
        model.register_forward_pre_hook(
            lambda mod, args: seen.append(args[0].detach().clone()) if mod.training else None)
        return model

    monkeypatch.setattr("flowmod.model.motion_resnet18", recording_model)
    train_model(tx, tdf, vx, vdf, tmp_path, **{**KW, "epochs": 1, "hflip_p": 0.5},
                in_channels=channels, flip_negate=negate)
    batches, flips = epoch_plan(len(tx), KW["batch_size"], 0.5, KW["seed"], 1)
    assert len(seen) == len(batches) and flips.any() and not flips.all()
    pos = 0
    for got, idx in zip(seen, batches, strict=True):
        want = torch.from_numpy(tx[idx].astype(np.float32))
        fl = torch.from_numpy(flips[pos : pos + len(idx)])
        pos += len(idx)
        want[fl] = torch.flip(want[fl], dims=(-1,))
        for c in negate:
            want[fl, c] = -want[fl, c]
        torch.testing.assert_close(got, want, rtol=0, atol=0)


def test_record_stores_unscored_probabilities_per_epoch(data, tmp_path) -> None:
    from flowmod.train import EPOCH_PROBS

    tx, tdf, vx, vdf = data
    hist = train_model(tx, tdf, vx, vdf, tmp_path, record=vx, **KW)
    probs = np.load(tmp_path / EPOCH_PROBS)
    assert probs.shape == (2, len(vx)) and ((probs >= 0) & (probs <= 1)).all()
    assert not any(c.startswith(("monitor", "test")) for c in hist.columns), "no test scores"
    last = predict(load_model(tmp_path / "last.pt"), vx, device="cpu")
    np.testing.assert_allclose(probs[-1], last, atol=1e-6)


def test_dataset_reopens_memmaps_in_workers(tmp_path) -> None:
    import pickle

    from flowmod.train import CropDataset

    arr = np.lib.format.open_memmap(tmp_path / "x.npy", mode="w+", dtype=np.float16,
                                    shape=(5, 2, 16, 16))
    arr[:] = np.arange(5, dtype=np.float16)[:, None, None, None]
    arr.flush()
    x = np.load(tmp_path / "x.npy", mmap_mode="r")
    ds = CropDataset(x, np.array([0, 1, 0, 1, 1]))
    blob = pickle.dumps(ds)
    assert len(blob) < 1000 < x.nbytes  # the array is not pickled, only its file name
    back = pickle.loads(blob)
    assert isinstance(back.x, np.memmap) and not back.x.flags.writeable  # reopened read-only
    xb, yb = back[[4, 1]]
    assert xb.dtype == torch.float16 and xb[:, 0, 0, 0].tolist() == [4.0, 1.0]  # as stored
    assert yb.dtype == torch.float32 and yb.tolist() == [1.0, 1.0]  # int labels as float32


def test_training_batches_from_the_device_or_streamed_are_the_same(tmp_path) -> None:
    """Crops that fit are held on the device and batched there; larger ones stream from
    their memmap: both give float32 batches equal to the stored crops (issue 40)."""
    from flowmod.train import ResidentCrops, StreamedCrops, crop_source

    rng = np.random.default_rng(3)
    x = rng.normal(0, 40, (9, 2, 6, 6)).astype(np.float16)
    np.save(tmp_path / "x.npy", x)
    xm = np.load(tmp_path / "x.npy", mmap_mode="r")
    y = (np.arange(9) % 2).astype(np.float32)
    cpu = torch.device("cpu")
    resident = crop_source(xm, y, cpu, resident_bytes=x.nbytes)
    streamed = crop_source(xm, y, cpu, resident_bytes=x.nbytes - 1)
    assert isinstance(resident, ResidentCrops) and isinstance(streamed, StreamedCrops)
    assert streamed.workers == 0 and crop_source(xm, y, cpu, 3, resident_bytes=0).workers == 3
    other = _PidCrops()  # not an array: streamed, whatever its size
    built = crop_source(other, np.arange(8) % 2, cpu, 2)
    assert isinstance(built, StreamedCrops) and built.ds.x is other and built.workers == 2
    assert built.dev == cpu and built.ds.y.tolist() == [0, 1] * 4
    assert crop_source(other, np.zeros(8), cpu).workers == 0
    plan = [np.array([0, 3, 8]), np.array([1, 2, 4, 5]), np.array([6, 7])]
    for (xa, ya), (xb, yb), idx in zip(resident.batches(plan), streamed.batches(plan), plan,
                                       strict=True):
        assert xa.dtype == xb.dtype == torch.float32
        np.testing.assert_array_equal(xa.numpy(), x[idx].astype(np.float32))
        assert torch.equal(xa, xb) and torch.equal(ya, yb) and ya.tolist() == y[idx].tolist()


def test_training_streamed_gives_the_weights_of_training_on_the_device(data, run_a, tmp_path
                                                                       ) -> None:
    tx, tdf, vx, vdf = data
    out_a, hist_a = run_a
    hist_b = train_model(tx, tdf, vx, vdf, tmp_path, **KW, resident_bytes=0)
    cols = [c for c in HISTORY_COLUMNS if c != "seconds"]
    pd.testing.assert_frame_equal(hist_a[cols], hist_b[cols], check_exact=True)
    _assert_same_weights(_state(out_a / "last.pt"), _state(tmp_path / "last.pt"))


def test_published_weights_in_float16_predict_as_the_float32_ones(data, run_a, tmp_path) -> None:
    """The stage keeps best.pt in float16: floating tensors halve, integer buffers stay, and
    the model loads back into float32 with the same decisions on the validation crops."""
    import shutil

    from flowmod.train import half_weights

    vx = data[2]
    half = tmp_path / "best.pt"
    shutil.copy(run_a[0] / "best.pt", half)
    half_weights(half)
    full, small = _state(run_a[0] / "best.pt"), _state(half)
    assert set(full) == set(small)
    for k, v in full.items():
        want = torch.float16 if v.is_floating_point() else v.dtype
        assert small[k].dtype == want, k
    assert half.stat().st_size < 0.55 * (run_a[0] / "best.pt").stat().st_size
    model = load_model(half)
    assert all(p.dtype == torch.float32 for p in model.parameters())
    p32 = predict(load_model(run_a[0] / "best.pt"), vx, device="cpu")
    p16 = predict(model, vx, device="cpu")
    assert np.abs(p32 - p16).max() < 5e-3
    assert ((p32 > 0.5) == (p16 > 0.5)).all()
    assert not np.array_equal(p32, p16)  # really rounded


# --- guards: each test below fails on one realistic one-line bug ----------------------------

def test_precision_and_recall_are_not_swapped() -> None:
    """tp 2, fp 1, fn 2: precision 2/3, recall 1/2 (a set where the two differ)."""
    y = np.array([1, 1, 1, 1, 0])
    p = np.array([0.9, 0.9, 0.1, 0.1, 0.9])
    m = ev.metrics(y, p)
    assert (m["precision"], m["recall"]) == pytest.approx((2 / 3, 1 / 2))
    assert m["f1"] == pytest.approx(2 * 2 / (2 * 2 + 1 + 2))
    s = ev.seed_summary(y, p[None], np.zeros(5))
    assert (s["precision"], s["recall"]) == pytest.approx((2 / 3, 1 / 2))


def test_interval_level_is_the_central_share() -> None:
    """A 90 % interval of 0..1000 spans the 5th to the 95th percentile, a 95 % one more."""
    reps = np.arange(1001, dtype=float)
    assert ev.interval(reps, 0.90) == pytest.approx((50.0, 950.0))
    assert ev.interval(reps, 0.95) == pytest.approx((25.0, 975.0))
    assert ev.interval(reps) == ev.interval(reps, 0.95)


def test_paired_comparison_draws_the_same_scenes_for_both() -> None:
    """B is A with one more wrong object in every scene: on any resample of whole scenes the
    difference stays near its value (paired); drawing B's scenes independently would spread
    it across the whole range of A's and B's F1."""
    rng = np.random.default_rng(3)
    scenes = np.repeat(np.arange(12), 10)
    y = (rng.random(len(scenes)) < 0.5).astype(int)
    good = np.where(rng.random(len(y)) < 0.3, 1 - y, y).astype(float)  # 70 % right
    worse = good.copy()
    for s in range(12):  # one more error per scene
        i = np.flatnonzero((scenes == s) & (good == y))[0]
        worse[i] = 1 - y[i]
    d = ev.paired_comparison(y, good, worse, scenes, n=2000, seed=0)
    lo, hi = d["ci"]
    assert 0 < lo <= d["delta_f1"] <= hi
    assert hi - lo < 0.06, f"paired: the difference barely moves, got {lo:.3f}-{hi:.3f}"
    a = ev.scene_bootstrap(y, good, scenes, n=2000, seed=0)
    b = ev.scene_bootstrap(y, worse, scenes, n=2000, seed=1)  # unpaired draws
    assert np.subtract(*ev.interval(a - b)[::-1]) > 2 * (hi - lo)


def test_train_settings_take_every_training_parameter() -> None:
    """Each training parameter of a profile reaches the trainer (none falls back to a
    default: the smoke and demo profiles share several values with the defaults)."""
    from flowmod.params import load_profile
    from flowmod.train import TrainSettings

    values = dict(epochs=5, batch_size=7, lr=0.02, momentum=0.8, weight_decay=0.003,
                  step_size=4, gamma=0.77, hflip_p=0.25, num_workers=2, device="cpu",
                  model_width=16, input_scaling="log")
    s = TrainSettings.of(load_profile("demo").model_copy(update={**values, "amp": "bf16"}))
    got = {k: getattr(s, {"model_width": "width", "input_scaling": "input_mode"}.get(k, k))
           for k in values}
    assert got == values and s.amp == "bf16"
    assert TrainSettings.of(load_profile("demo").model_copy(update={"amp": "off"})).amp is None


def test_an_empty_checkpoint_is_one_clear_error(tmp_path) -> None:
    """A 0-byte best.pt (a copy cut short): torch's EOFError has no message; the error still
    names the file and what to do."""
    path = tmp_path / "best.pt"
    path.write_bytes(b"")
    with pytest.raises(CheckpointError, match=r"best.pt: not a readable checkpoint .*retrain"):
        load_model(path)


def _stage_params(**update):
    """The demo profile's training settings cut to this file's tiny CPU runs (seed 7)."""
    from flowmod.params import load_profile

    return load_profile("demo").model_copy(update=dict(
        epochs=2, batch_size=16, model_width=16, device="cpu", amp="off", seed=7, force=False,
        num_workers=0, input_scaling="log", **update))


def test_the_stage_trainer_seeds_by_part_keeps_a_float16_best_and_no_last(data, tmp_path) -> None:
    """train_seed: part f1s2 trains with seed ``seed + 1 + 100*2`` and the profile's
    settings, in the folder ``b.start`` gives (fresh only with ``force``); then best.pt is
    float16, last.pt is gone, and the manifest fields say what was trained."""
    from types import SimpleNamespace

    from flowmod import dag, train

    tx, tdf, vx, vdf = data
    q = _stage_params()
    fresh = []

    def start(fresh_: bool = False, **kw) -> Path:
        fresh.append(kw.get("fresh", fresh_))
        return tmp_path

    b = SimpleNamespace(params=q, node=dag.Node("train", "dis", "f1s2"), start=start)
    info = train.train_seed(b, (tx, tdf), (vx, vdf), False, "dis")
    hist = pd.read_csv(tmp_path / "history.csv")
    assert fresh == [False]
    assert info == {"best_epoch": int(hist["val_f1"].to_numpy().argmax()) + 1,
                    "best_f1": pytest.approx(hist["val_f1"].max()), "seed": 208,
                    "amp": "off", "input_scaling": "log", "width": q.model_width}
    assert isinstance(info["best_epoch"], int) and isinstance(info["best_f1"], float)
    assert not (tmp_path / "last.pt").exists()
    state = _state(tmp_path / "best.pt")
    assert {v.dtype for v in state.values() if v.is_floating_point()} == {torch.float16}
    # the same seed trained directly gives the same validation history
    direct = train_model(tx, tdf, vx, vdf, tmp_path / "direct", train.TrainSettings.of(q),
                         seed=208, progress=False)
    np.testing.assert_allclose(hist["val_loss"], direct["val_loss"], rtol=1e-6)
    b.params = q.model_copy(update={"force": True})
    info = train.train_seed(b, (tx, tdf), (vx, vdf), False, "dis", input_mode="raw")
    assert fresh == [False, True] and info["input_scaling"] == "raw"


def test_a_model_s_recipe_comes_from_its_flow_and_crops_manifests(tmp_path) -> None:
    """recipe: the flow node's method parameters, dtype and store scale and the crops
    node's size and scale; absent manifests give Nones, not an error."""
    import json
    from types import SimpleNamespace

    from flowmod import train

    def write(node, rec):
        (tmp_path / node).mkdir(parents=True)
        (tmp_path / node / "manifest.json").write_text(json.dumps(
            {"fingerprint": "x", **rec}))

    b = SimpleNamespace(other=lambda n: tmp_path / n.stage / n.method / n.part)
    write("flow/dis/keyframe", {"params": {"preset": 2}, "dtype": "float16",
                                 "store_scale": 0.5})
    write("crops/dis/keyframe", {"params": {"crop_size": 224, "crop_scale": 1.5}})
    assert train.recipe(b, "dis") == {"method": "dis", "flow_params": {"preset": 2},
                                      "flow_dtype": "float16", "store_scale": 0.5,
                                      "crop_size": 224, "crop_scale": 1.5}
    assert train.recipe(b, "dis", part="other") == {
        "method": "dis", "flow_params": {"preset": 2}, "flow_dtype": "float16",
        "store_scale": 0.5, "crop_size": None, "crop_scale": None}
    assert train.recipe_from("gt", {}, {}) == {
        "method": "gt", "flow_params": {}, "flow_dtype": None, "store_scale": None,
        "crop_size": None, "crop_scale": None}


def test_extension_parts_follow_the_extension_seeds() -> None:
    from flowmod.params import load_profile
    from flowmod.train import extension_parts

    p = load_profile("demo")
    assert extension_parts(p.model_copy(update={"folds": 3, "extension_seeds": 2})) == [
        "f0s0", "f0s1", "f1s0", "f1s1", "f2s0", "f2s1"]
    assert extension_parts(p.model_copy(update={"folds": 1, "extension_seeds": 2,
                                                "seeds": 5})) == ["s0", "s1"]


class _PidCrops:
    """An array-like of crops that records which process assembled each batch."""

    shape = (8, 2, 4, 4)

    def __len__(self) -> int:
        return 8

    def __getitem__(self, idx):
        import os

        return np.full((len(idx), 2, 4, 4), os.getpid(), np.float32)


def test_the_batch_sources_keep_labels_float32_host_crops_on_the_cpu_and_use_workers() -> None:
    """ResidentCrops on the CPU gathers from host memory (no device copy) with float32
    labels; StreamedCrops reads through ``workers`` processes (none by default)."""
    import os

    from flowmod.train import ResidentCrops, StreamedCrops

    cpu = torch.device("cpu")
    x = np.arange(4 * 2 * 2 * 2, dtype=np.float16).reshape(4, 2, 2, 2)
    resident = ResidentCrops(x, np.array([0, 1, 1, 0]), cpu)
    assert resident.x is None and resident.y.dtype == torch.float32
    streamed = StreamedCrops(_PidCrops(), np.zeros(8), cpu)
    assert streamed.workers == 0
    plan = [np.array([0, 1]), np.array([2, 3])]
    assert {int(xb[0, 0, 0, 0]) for xb, _ in streamed.batches(plan)} == {os.getpid()}
    pids = {int(xb[0, 0, 0, 0]) for xb, _ in StreamedCrops(_PidCrops(), np.zeros(8), cpu,
                                                             workers=1).batches(plan)}
    assert len(pids) == 1 and os.getpid() not in pids


class _Unpickled:
    """An object whose unpickling leaves a mark (what a hostile checkpoint could run)."""

    def __reduce__(self):
        return (_UNPICKLED.append, ("ran",))


_UNPICKLED: list[str] = []


def test_checkpoints_are_read_without_unpickling_code(data, run_a, tmp_path) -> None:
    """A last.pt or best.pt that holds a pickled object is refused before it can run any
    code (``weights_only=True``); a checkpoint of another format is named as such."""
    from flowmod.train import half_weights

    tx, tdf, vx, vdf = data
    for name in ("last.pt", "best.pt"):
        torch.save({"format": 1, "x": _Unpickled()}, tmp_path / name)
    with pytest.raises(Exception, match="(?i)weights.only"):
        train_model(tx, tdf, vx, vdf, tmp_path, **KW)
    with pytest.raises(Exception, match="(?i)weights.only"):
        half_weights(tmp_path / "best.pt")
    assert _UNPICKLED == []
    torch.save({"format": "other"}, tmp_path / "last.pt")
    with pytest.raises(TrainingError, match=r"last.pt: not a flowmod training checkpoint"):
        train_model(tx, tdf, vx, vdf, tmp_path, **KW)


def test_a_checkpoint_records_the_settings_and_data_it_was_made_with() -> None:
    """_config: what a resume must match, by name (the refusal names them); the paper's
    input, network and scaling keep the short config older checkpoints have."""
    from dataclasses import replace

    from flowmod.train import TrainSettings, _config

    s = TrainSettings(batch_size=8, lr=0.02, momentum=0.8, weight_decay=0.001, step_size=4,
                      gamma=0.3, hflip_p=0.25)
    x = np.zeros((5, 2, 12, 12), np.float16)
    y_tr, y_va = np.array([0, 1, 1, 0, 1.0]), np.array([1, 0, 0.0])
    base = {"batch_size": 8, "lr": 0.02, "momentum": 0.8, "weight_decay": 0.001,
            "step_size": 4, "gamma": 0.3, "hflip_p": 0.25, "seed": 7, "amp": "None",
            "crop_size": 12, "n_train": 5, "n_train_moving": 3, "n_val": 3, "n_val_moving": 1}
    assert _config(s, 7, None, x, y_tr, y_va, 2, (0,)) == base
    assert _config(s, 7, "bf16", x, y_tr, y_va, 2, (0,))["amp"] == "bf16"
    assert _config(s, 7, None, x, y_tr, y_va, 3, (0,)) == {**base, "channels": 3,
                                                           "flip_negate": [0]}
    assert _config(s, 7, None, x, y_tr, y_va, 2, (0, 1)) == {**base, "channels": 2,
                                                             "flip_negate": [0, 1]}
    wide = replace(s, width=16, input_mode="log")
    assert _config(wide, 7, None, x, y_tr, y_va, 2, (0,), flow_channels=(1,)) == {
        **base, "width": 16, "input_mode": "log", "flow_channels": [1]}


def test_a_new_run_has_the_settings_optimiser_and_schedule(monkeypatch) -> None:
    """_new_run: SGD with Table 2's lr, momentum and weight decay, StepLR with its step and
    gamma, the model built for the run's channels, width, scaling and flow channels, seeded;
    no loss scaling without fp16."""
    import flowmod.train as tr

    built = []
    monkeypatch.setattr("flowmod.model.motion_resnet18",
                        lambda *a: built.append(a) or motion_resnet18(*a))
    s = tr.TrainSettings(lr=0.02, momentum=0.8, weight_decay=0.003, step_size=4, gamma=0.3,
                         width=8, input_mode="log")
    run = tr._new_run(s, 3, 11, torch.device("cpu"), None, (0, 2))
    assert built == [(3, 8, "log", (0, 2))]
    group = run.opt.param_groups[0]
    assert isinstance(run.opt, torch.optim.SGD)
    assert (group["lr"], group["momentum"], group["weight_decay"]) == (0.02, 0.8, 0.003)
    assert (run.sched.step_size, run.sched.gamma) == (4, 0.3)
    assert not run.scaler.is_enabled()
    again = tr._new_run(s, 3, 11, torch.device("cpu"), None, (0, 2))
    _assert_same_weights(run.model.state_dict(), again.model.state_dict())


def test_automatic_mixed_precision_is_resolved_per_device() -> None:
    from flowmod.train import _resolve_amp

    cpu = torch.device("cpu")
    assert [_resolve_amp(a, cpu) for a in ("auto", None, "none", "bf16", "fp16")] == [
        None, None, None, "bf16", "fp16"]
    with pytest.raises(ValueError, match=r"amp='fp32': use 'auto', None, 'bf16' or 'fp16'"):
        _resolve_amp("fp32", cpu)


def test_an_epoch_s_training_loss_is_the_mean_over_its_crops(data, tmp_path, capsys,
                                                            monkeypatch) -> None:
    """With lr 0 the weights stay as initialised, so the first epoch's training loss is the
    crop-weighted mean of each planned batch's loss in training mode (BatchNorm on the
    batch), computed here batch by batch. Without ``progress`` nothing is printed."""
    from torch import nn

    tx, tdf, vx, vdf = data
    kw = {**KW, "epochs": 1, "lr": 0.0, "momentum": 0.0, "weight_decay": 0.0, "hflip_p": 0.0,
          "batch_size": 24, "input_mode": "log"}  # 64 crops: batches of 24, 24 and 16
    del kw["seed"]  # the default, 0
    out = tmp_path / "deep" / "run"  # made with its parents
    import flowmod.train as tr

    sources = []
    source = tr.crop_source
    monkeypatch.setattr(tr, "crop_source", lambda *a: sources.append(a[3:]) or source(*a))
    hist = train_model(tx, tdf, vx, vdf, out, flow_channels=(0,), num_workers=0,
                       resident_bytes=10**9, **kw)
    assert sources == [(0, 10**9)]  # the settings' workers and resident limit
    assert capsys.readouterr().err == ""
    config = torch.load(out / "last.pt", weights_only=True)["config"]
    assert (config["seed"], config["input_mode"], config["flow_channels"]) == (0, "log", [0])
    assert "channels" not in config and config["width"] == KW["width"]
    torch.manual_seed(0)
    model = motion_resnet18(2, KW["width"], "log", (0,)).train()
    batches, _ = epoch_plan(len(tx), 24, 0.0, 0, 1)
    y = tdf["label"].to_numpy(np.float32)
    with torch.no_grad():
        losses = [nn.functional.binary_cross_entropy_with_logits(
            model(torch.from_numpy(tx[idx].astype(np.float32))).reshape(-1),
            torch.from_numpy(y[idx])).item() * len(idx) for idx in batches]
    assert [len(b) for b in batches] == [24, 24, 16]
    assert hist["train_loss"].iloc[0] == pytest.approx(sum(losses) / len(tx), rel=1e-5)
    assert 0 < hist["seconds"].iloc[0] < 600  # the epoch's own wall time


def test_the_epoch_plan_is_the_one_the_published_models_were_trained_with() -> None:
    """The order and flips of (seed, epoch) are fixed: a published model retrains bit for
    bit only with the same plan."""
    batches, flips = epoch_plan(10, 4, 0.5, 3, 2)
    assert [b.tolist() for b in batches] == [[0, 4, 6, 9], [1, 2, 5, 8], [3, 7]]
    assert flips.astype(int).tolist() == [1, 1, 0, 0, 0, 0, 1, 0, 0, 0]
    batches, flips = epoch_plan(10, 4, 0.5, 0, 1)
    assert [b.tolist() for b in batches] == [[1, 2, 5, 6], [0, 3, 8, 9], [4, 7]]
    assert flips.astype(int).tolist() == [1, 0, 0, 0, 1, 1, 1, 0, 1, 0]
    # a crop is flipped when its draw is below hflip_p: seed 27's draw 26564 is 0.5 itself
    _, flips = epoch_plan(1 << 16, 64, 0.5, 27, 1)
    assert not flips[26564] and 0.45 < flips.mean() < 0.55


def test_an_epoch_that_ties_the_best_validation_f1_keeps_the_earlier_weights(tmp_path) -> None:
    """_end_epoch: the best epoch changes only on a strictly higher validation F1."""
    from types import SimpleNamespace

    from torch import nn

    from flowmod.train import TrainSettings, _end_epoch

    class Fixed(nn.Module):  # the same logits every epoch: +1 on u > 0, else -1
        def __init__(self) -> None:
            super().__init__()
            self.w = nn.Parameter(torch.ones(1))

        def forward(self, x):
            return torch.where(x[:, 0, 0, 0] > 0, self.w, -self.w)[:, None]

    vx = np.zeros((4, 2, 4, 4), np.float32)
    vx[:2, 0] = 1.0
    y = np.array([1.0, 0.0, 1.0, 0.0])  # F1 0.5 every epoch
    run = SimpleNamespace(model=Fixed(), sched=SimpleNamespace(step=lambda: None), rows=[],
                          best_f1=-1.0, best_epoch=0, epoch=0)
    for epoch in (1, 2):
        _end_epoch(run, epoch, 0.5, 0.01, time.perf_counter(), vx, y, None, tmp_path,
                   TrainSettings(), torch.device("cpu"), None)
        if epoch == 1:
            first = (tmp_path / "best.pt").stat().st_mtime_ns
            run.model.w.data.fill_(2.0)
    assert (run.best_epoch, run.best_f1, run.epoch) == (1, 0.5, 2)
    assert (tmp_path / "best.pt").stat().st_mtime_ns == first
    assert torch.load(tmp_path / "best.pt", weights_only=True)["w"].item() == 1.0


def test_the_validation_loss_is_the_stable_binary_cross_entropy() -> None:
    """_bce_with_logits equals -mean(y log p + (1 - y) log(1 - p)), p = sigmoid(z), also
    where |z| is large (computed here in long double)."""
    from flowmod.train import _bce_with_logits

    z = np.array([-30.0, -2.0, -0.1, 0.0, 0.7, 3.0, 25.0], np.float32)
    y = np.array([1, 0, 1, 0, 1, 1, 0], np.float32)
    zl = z.astype(np.longdouble)
    p = 1 / (1 + np.exp(-zl))
    want = float(-np.mean(y * np.log(p) + (1 - y) * np.log1p(-p)))
    assert _bce_with_logits(z, y) == pytest.approx(want, rel=1e-9)


def test_the_stage_trainer_resumes_and_passes_the_input_on(data, tmp_path, capsys) -> None:
    """train_seed resumes a killed build's last.pt and hands train_model the record, the
    progress flag and the input's channels, flips and scaled channels: its history is that
    of train_model with the same arguments, resumed from the same checkpoint."""
    from types import SimpleNamespace

    from flowmod import dag, train

    tx, tdf, vx, vdf = data
    tx3, vx3 = (np.concatenate([a, a[:, :1]], axis=1) for a in (tx, vx))
    q = _stage_params(hflip_p=0.5)
    args = dict(in_channels=3, flip_negate=(0, 2), flow_channels=(0,))
    first = {}
    for folder in ("stage", "direct"):  # a killed build: epoch 1 and its last.pt
        first[folder] = train_model(
            tx3, tdf, vx3, vdf, tmp_path / folder, train.TrainSettings.of(q), seed=207,
            progress=False, record=vx3[:5], **{**args, "epochs": 1})
    b = SimpleNamespace(params=q, node=dag.Node("train", "dis", "f0s2"),
                        start=lambda fresh=False: tmp_path / "stage")
    capsys.readouterr()
    train.train_seed(b, (tx3, tdf), (vx3, vdf), True, "dis", record=vx3[:5], **args)
    assert "train dis seed 207" in capsys.readouterr().err
    direct = train_model(tx3, tdf, vx3, vdf, tmp_path / "direct", train.TrainSettings.of(q),
                         seed=207, progress=False, record=vx3[:5], **args)
    got = pd.read_csv(tmp_path / "stage" / "history.csv")
    np.testing.assert_allclose(got["val_loss"], direct["val_loss"], rtol=1e-6)
    np.testing.assert_allclose(np.load(tmp_path / "stage" / train.EPOCH_PROBS),
                               np.load(tmp_path / "direct" / train.EPOCH_PROBS), rtol=1e-5)
    assert len(got) == 2 and got["seconds"].iloc[0] == pytest.approx(
        first["stage"]["seconds"].iloc[0])  # epoch 1 was resumed, not retrained
