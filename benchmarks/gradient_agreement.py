"""What benchmarks/grad_vs_gsplat.py and grad_vs_reference.py share: the Trainer's model taken to chosen steps, the
op's inputs from its raw parameters, per-parameter agreement of two gradient sets, and the primitives whose sh0
gradients differ most, with what they are."""
from __future__ import annotations

import sys
import tempfile

import torch

from common import ROOT

sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from reference import sh_to_rgb  # noqa: E402  (the test suite's float64 oracle)

from warpgs.train.trainer import Trainer  # noqa: E402

NAMES = ("means", "log_scales", "quats", "logit_opacities", "sh0", "shN")


def render_inputs(params: dict, degree: int) -> tuple:
    """(means, quats, scales, opacities, SH coefficients) as the render ops take them, from the raw parameters."""
    k = (degree + 1) ** 2
    colors = torch.cat([params["sh0"], params["shN"][:, : k - 1]], 1)
    return (params["means"], params["quats"], torch.exp(params["log_scales"]), torch.sigmoid(params["logit_opacities"]),
            colors)


def trained_at(cfg, marks, num_views: int):
    """Yields (mark, trainer, views) with the Trainer's model trained to each step in `marks` (ascending) and its SH
    degree set as the schedule has it there; views: its first `num_views` training views. Outputs go to a
    temporary folder."""
    with tempfile.TemporaryDirectory() as tmp:
        cfg.output.dir = tmp
        trainer = Trainer(cfg, quiet=True)
        views = [trainer.view(i) for i in trainer.scene.train[:num_views]]
        for mark in marks:
            while trainer.step < mark:
                trainer.train_step()
            trainer.model.active_sh_degree = min(trainer.model.max_sh_degree, mark // max(cfg.model.sh_interval, 1))
            yield mark, trainer, views


def agreement(a: dict, b: dict) -> dict:
    """Per parameter of NAMES: cosine similarity ("<name>_cos") and L2 error relative to b ("<name>_rel_err")."""
    row = {}
    for k in NAMES:
        x, y = a[k].double().flatten(), b[k].double().flatten()
        row[f"{k}_cos"] = float(x @ y / (x.norm() * y.norm()).clamp_min(1e-300))
        row[f"{k}_rel_err"] = float((x - y).norm() / y.norm().clamp_min(1e-300))
    return row


@torch.no_grad()
def sh0_outliers(trainer: Trainer, view, ours: dict, theirs: dict, k: int, other: str) -> list:
    """The k primitives whose summed sh0 gradients differ most between `ours` (warpgs) and `theirs` (named
    `other`), with what might explain it: their sh0, position and opacity gradients on both sides, and, seen from
    `view`, camera depth, pixel position, opacity, scales and colour (SH + 0.5 clamped at 0). Printed as well."""
    m = trainer.model
    diff = (ours["sh0"].double() - theirs["sh0"].double()).reshape(len(m.means), -1).norm(dim=1)
    top = diff.topk(min(k, len(diff)))
    p = m.means @ view.viewmat[:3, :3].T + view.viewmat[:3, 3]
    z = p[:, 2]
    u = view.K[0, 0] * p[:, 0] / z + view.K[0, 2]
    v = view.K[1, 1] * p[:, 1] / z + view.K[1, 2]
    centre = -view.viewmat[:3, :3].T @ view.viewmat[:3, 3]
    rows = []
    for i in top.indices.tolist():
        d = m.means[i] - centre
        sh = torch.cat([m.params["sh0"][i], m.params["shN"][i]], 0)[None].double()
        colour = sh_to_rgb(sh, m.active_sh_degree, (d / d.norm())[None].double())[0]
        rows.append({"index": i, "diff": float(diff[i]), "warpgs": ours["sh0"][i].flatten().tolist(),
                     other: theirs["sh0"][i].flatten().tolist(),
                     "means_grad_warpgs": ours["means"][i].tolist(), f"means_grad_{other}": theirs["means"][i].tolist(),
                     "opacity_grad_warpgs": float(ours["logit_opacities"][i]),
                     f"opacity_grad_{other}": float(theirs["logit_opacities"][i]),
                     "depth": float(z[i]), "u": float(u[i]), "v": float(v[i]), "opacity": float(m.opacities[i]),
                     "scales": m.scales[i].tolist(), "sh0": m.params["sh0"][i].flatten().tolist(),
                     "colour_clamped_at_0": colour.tolist()})
    share = float(top.values.pow(2).sum() / diff.pow(2).sum().clamp_min(1e-300))
    print(f"top {k} sh0 gradient differences carry {100 * share:.1f}% of the squared difference", flush=True)
    for r in rows:
        print("   ", {key: (round(val, 5) if isinstance(val, float) else
                            [round(x, 6) for x in val] if isinstance(val, list) else val) for key, val in r.items()},
              flush=True)
    return rows
