"""The learned local untangling operator of thesis ch. 7.3.2 (eq. 7.7, §7.5.2), and how it
compares with the exact one (``inference.untangle.untangle_exact``).

    theta = argmin sum |O(f*, h*, theta) - f_GT|_1,   f_GT = O(f*, h*) exact               (7.7)

Architecture as §7.5.2: an MLP over [f*, h*] (2N = 14 inputs, N = 7 layer slots; an outfit with
fewer layers sets h* = 1 in the unused ones), 4 hidden layers of 256, ELU. One change: the MLP
outputs the correction f - f*, added to f* (an untangled value equals its input wherever the point
is not tangled, which is most of the samples; the residual makes that the zero output). Training
data as §7.5.2: f* ~ U(-0.2, 1.5), h* ~ U(-1, 1), 1 million samples (``training.untangle``),
Adam from 1e-3 with a linear decay to 1e-3 of it; fewer epochs than the thesis' 3000 on a CPU.

    python -m training.train_untangler [--epochs 20] [--out build/untangler]

writes ``untangler.onnx`` (inputs f_star, h_star (B, 7) float32; output f (B, 7)) and
``report.json``: error against the exact operator on fresh samples (mean, p99, max), the share of
outputs still tangled (``inference.untangle.tangled``), and both operators' time for 5,000 points.
Units: whatever the fields' (metres for f); h is unitless.
"""
from __future__ import annotations

import argparse
import json
import logging
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from inference.untangle import tangled, untangle_exact
from training.datasets import REPO_ROOT
from training.untangle import MAX_LAYERS, sample_untangling

log = logging.getLogger(__name__)

OUT_DIR = REPO_ROOT / "build" / "untangler"


class UntanglerMLP(nn.Module):
    """f = f* + MLP([f*, h*]) (module doc)."""

    def __init__(self, layers: int = MAX_LAYERS, hidden: int = 256, depth: int = 4):
        super().__init__()
        dims = [2 * layers] + [hidden] * depth
        blocks: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:]):
            blocks += [nn.Linear(a, b), nn.ELU()]
        self.net = nn.Sequential(*blocks, nn.Linear(hidden, layers))

    def forward(self, f_star: torch.Tensor, h_star: torch.Tensor) -> torch.Tensor:
        return f_star + self.net(torch.cat([f_star, h_star], -1))


def train(model: UntanglerMLP, samples: int, epochs: int, batch: int, lr: float, seed: int, loss_kind: str = "mse") -> list[float]:
    """Adam over a fixed sample set on the L1 loss of eq. 7.7 (``loss_kind="l1"``) or the squared
    error (module doc: what each learned); the mean loss of each epoch."""
    rng = np.random.default_rng(seed)
    f_star, h_star, f_gt = (torch.as_tensor(a) for a in sample_untangling(samples, rng))
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    steps = epochs * (samples // batch)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: 1.0 - (1.0 - 1e-3) * min(k / steps, 1.0))
    gen = torch.Generator().manual_seed(seed)
    history = []
    for epoch in range(epochs):
        order = torch.randperm(samples, generator=gen)
        total, t0 = 0.0, time.perf_counter()
        for k in range(samples // batch):
            idx = order[k * batch:(k + 1) * batch]
            r = model(f_star[idx], h_star[idx]) - f_gt[idx]
            loss = (r.abs() if loss_kind == "l1" else r.square()).sum(-1).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item()
        history.append(total / (samples // batch))
        log.info("epoch %d: L1 %.5f (%.0f s)", epoch, history[-1], time.perf_counter() - t0)
    return history


def export(model: UntanglerMLP, path: Path, tolerance: float = 1e-5) -> float:
    """untangler.onnx, with torch-onnxruntime parity on random samples (the largest difference)."""
    import onnxruntime as ort

    from training.export_onnx import OPSET

    model = model.eval()
    example = (torch.zeros(2, MAX_LAYERS), torch.ones(2, MAX_LAYERS))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(model, example, str(path), input_names=["f_star", "h_star"], output_names=["f"], opset_version=OPSET,
                          dynamo=False, dynamic_axes={"f_star": {0: "B"}, "h_star": {0: "B"}, "f": {0: "B"}})
    f_star, h_star, _ = sample_untangling(1000, np.random.default_rng(3))
    (y,) = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"f_star": f_star, "h_star": h_star})
    with torch.no_grad():
        worst = float(np.abs(y - model(torch.as_tensor(f_star), torch.as_tensor(h_star)).numpy()).max())
    if not worst <= tolerance:
        raise RuntimeError(f"{path.name}: parity {worst:.3g} exceeds {tolerance}")
    return worst


def tangle_depth(f: np.ndarray, h: np.ndarray) -> np.ndarray:
    """(n,) how deep a point is tangled: the largest min(-f_i, f_j) over active i < j (<= 0: not
    tangled). ``inference.untangle.tangled`` counts any depth; an approximate operator leaves
    depths of micrometres, so the report counts those past 1 mm."""
    active = h < 0.0
    inside = np.maximum.accumulate(np.where(active, -f, -np.inf), -1)
    return np.max(np.minimum(inside[..., :-1], np.where(active, f, -np.inf)[..., 1:]), -1)


def _best_ms(fn, repeats: int = 20) -> float:
    fn()
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def evaluate(path: Path, samples: int = 200_000, seed: int = 11) -> dict:
    """The ONNX operator against the exact one on fresh samples, per number of active layers (the
    unused slots at h* = 1, as an outfit of that many layers), and both operators' time on one
    thread for 5,000 points (thesis table 7.3)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(seed)
    report: dict = {"layers": {}}
    for n in (2, 3, 7):
        f_star, h_star, _ = sample_untangling(samples, rng, n)
        f_star = np.concatenate([f_star, rng.uniform(-0.2, 1.5, (samples, MAX_LAYERS - n)).astype(np.float32)], 1)
        h_star = np.concatenate([h_star, np.ones((samples, MAX_LAYERS - n), np.float32)], 1)
        exact = untangle_exact(f_star, h_star).astype(np.float32)
        (pred,) = sess.run(None, {"f_star": f_star, "h_star": h_star})
        err = np.abs(pred - exact)
        changed = np.abs(exact - f_star).max(1) > 0
        depth_in, depth_out = tangle_depth(f_star, h_star), tangle_depth(pred, h_star)
        pts_f, pts_h = f_star[:5000], h_star[:5000]
        report["layers"][n] = {
            "mean_abs": float(err.mean()),
            "p99_abs": float(np.quantile(err, 0.99)),
            "max_abs": float(err.max()),
            "mean_abs_where_tangled": float(err[changed].mean()),
            "identity_mean_abs_where_tangled": float(np.abs(exact - f_star)[changed].mean()),
            "tangled_input_share": float(tangled(f_star, h_star).mean()),
            "tangled_output_share": float(tangled(pred, h_star).mean()),
            "tangled_past_1mm_input_share": float((depth_in > 1e-3).mean()),
            "tangled_past_1mm_output_share": float((depth_out > 1e-3).mean()),
            "deepest_output_tangle": float(depth_out.max()),
            "ms_5000_exact_numpy": _best_ms(lambda: untangle_exact(pts_f, pts_h)),
            "ms_5000_onnx": _best_ms(lambda: sess.run(None, {"f_star": pts_f, "h_star": pts_h})),
        }
        log.info("%d layers: %s", n, report["layers"][n])
    return report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=OUT_DIR)
    p.add_argument("--samples", type=int, default=1_000_000)
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--batch", type=int, default=512)
    p.add_argument("--loss", choices=("mse", "l1"), default="mse")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--hidden", type=int, default=256)
    p.add_argument("--depth", type=int, default=4)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    torch.manual_seed(args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    model = UntanglerMLP(hidden=args.hidden, depth=args.depth)
    t0 = time.perf_counter()
    history = train(model, args.samples, args.epochs, args.batch, args.lr, args.seed, args.loss)
    wall = time.perf_counter() - t0
    path = args.out / "untangler.onnx"
    parity = export(model, path)
    report = {"config": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}, "train_s": wall,
              "history": history, "parity_max_abs": parity, "bytes": path.stat().st_size, **evaluate(path)}
    (args.out / "report.json").write_text(json.dumps(report, indent=1) + "\n")
    log.info("wrote %s (%.0f s of training)", args.out, wall)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
