"""The 3D projection's adjoint, run for every Gaussian (`project_gaussians`) against run only for those with an
upstream gradient (`project_gaussians_reached`, what the renderer launches) and the written-out one
(`kernels/project_adjoint.py`, raster option project_adjoint="written"), in one process, for several fractions
of Gaussians that reach a pixel (a 360° capture sees a part of its Gaussians from any one camera). With
--camera-grads the camera is differentiated too, also with one camera row per Gaussian (what the renderer does then).

    python benchmarks/project_adjoint.py                              # CPU, 100k Gaussians, SH degree 3
    python benchmarks/project_adjoint.py --device cuda --n 1000000 --repeats 50

Writes benchmarks/results/project_adjoint_<device>.json (or $OUT/...).
"""
from __future__ import annotations

import argparse
import statistics
import sys

import numpy as np
import warp as wp

from common import ROOT, time_call, write_json

sys.path.insert(0, str(ROOT))

from kernels import project, project_adjoint  # noqa: E402


def arrays(n: int, device: str, camera_grads: bool, seed: int = 0) -> dict:
    """Random Gaussians in front of a camera at the origin (OpenCV, looking down +z), SH degree 3; camera_grads:
    the camera's gradients are wanted too (pose optimisation: every Gaussian adds into one matrix)."""
    rng = np.random.default_rng(seed)
    means = np.c_[rng.uniform(-2, 2, (n, 2)), rng.uniform(2, 6, n)].astype(np.float32)
    quats = rng.normal(size=(n, 4)).astype(np.float32)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    a = lambda x, dt: wp.array(x, dtype=dt, device=device)  # noqa: E731
    z = lambda dt: wp.zeros(n, dtype=dt, device=device)  # noqa: E731
    return dict(
        means=a(means, wp.vec3), quats=a(quats, wp.vec4),
        scales=a(rng.uniform(-4, -2, (n, 3)).astype(np.float32), wp.vec3),
        coeffs=wp.array(rng.normal(0, 0.2, (n, 16, 3)).astype(np.float32), dtype=wp.vec3, device=device),
        viewmat=a(np.eye(4, dtype=np.float32)[None], wp.mat44),
        intrinsics=a(np.array([[800.0, 800.0, 640.0, 360.0]], np.float32), wp.vec4),
        outs=[z(wp.vec2), z(wp.vec3), z(wp.vec3), z(float), z(wp.vec3), z(wp.int32)],
        grads=[z(wp.vec3), z(wp.vec4), z(wp.vec3), wp.zeros((n, 16), dtype=wp.vec3, device=device)]
        + ([wp.zeros(1, dtype=wp.mat44, device=device), wp.zeros(1, dtype=wp.vec4, device=device)] if camera_grads
           else [None, None]))


def upstream(n: int, fraction: float, device: str, seed: int = 1) -> list:
    """Gradients of (means2d, conics, colors, depths): random for `fraction` of the Gaussians, zero elsewhere."""
    rng = np.random.default_rng(seed)
    hit = (rng.random(n) < fraction).astype(np.float32)
    g = lambda k: (rng.normal(size=(n, k)) * hit[:, None]).astype(np.float32)  # noqa: E731
    return [wp.array(g(2), dtype=wp.vec2, device=device), wp.array(g(3), dtype=wp.vec3, device=device),
            wp.array(g(3), dtype=wp.vec3, device=device), wp.array(g(1)[:, 0], dtype=float, device=device)]


def launcher(kernel, A: dict, g: list, n: int, device: str, camera_rows: bool = False):
    """The adjoint launch; camera_rows: one camera copy and gradient row per Gaussian, summed after (what the
    renderer does when the camera's gradient is wanted, render/camera_rows.py)."""
    settings = [1280, 720, 0.01, 1e10, project.COLOR_SH, 3, 0.3]
    camera, g_camera = [A["viewmat"], A["intrinsics"]], A["grads"][4:]
    if camera_rows:
        camera = [wp.array(np.repeat(a.numpy(), n, 0), dtype=a.dtype, device=device) for a in camera]
        g_camera = [wp.zeros(n, dtype=a.dtype, device=device) for a in camera]
    inputs = [A["means"], A["quats"], A["scales"], A["coeffs"]] + camera + settings + A["outs"]
    g_means2d, g_conics, g_colors, g_depths = g
    adj = A["grads"][:4] + g_camera + [0, 0, 0.0, 0.0, 0, 0, 0.0, g_means2d, g_conics, None, g_depths, g_colors, None]
    if kernel is project.project_gaussians_reached:
        inputs, adj = inputs + g, adj + [None] * 4

    def run():
        wp.launch(kernel, dim=n, inputs=inputs, adj_inputs=adj, adjoint=True, device=device)
        if camera_rows:
            for rows in g_camera:
                wp.to_torch(rows).sum(0)
    return run


def written_launcher(A: dict, g: list, n: int, device: str):
    """kernels/project_adjoint.py's adjoint on the same inputs (the renderer's raster option project_adjoint)."""
    want = (project_adjoint.WANT_MEANS | project_adjoint.WANT_QUATS | project_adjoint.WANT_SCALES
            | project_adjoint.WANT_COEFFS)
    inputs = ([A["means"], A["quats"], A["scales"], A["coeffs"], A["viewmat"], A["intrinsics"],
               1280, 720, 0.01, project.COLOR_SH, 3, 0.3] + list(g) + [want] + A["grads"][:4])
    return lambda: wp.launch(project_adjoint.project_gaussians_adjoint, dim=n, inputs=inputs, device=device)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--n", type=int, default=100000)
    ap.add_argument("--fractions", default="1,0.5,0.2", help="fractions of Gaussians with an upstream gradient")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=3, help="interleaved timing rounds")
    ap.add_argument("--camera-grads", action="store_true", help="also differentiate the camera (pose optimisation)")
    args = ap.parse_args(argv)
    wp.init()
    A = arrays(args.n, args.device, args.camera_grads)
    rows = []
    for fraction in (float(f) for f in args.fractions.split(",")):
        g = upstream(args.n, fraction, args.device)
        runs = {"all": launcher(project.project_gaussians, A, g, args.n, args.device),
                "reached": launcher(project.project_gaussians_reached, A, g, args.n, args.device)}
        if not args.camera_grads:  # the written-out adjoint covers an undifferentiated camera only
            runs["written"] = written_launcher(A, g, args.n, args.device)
        if args.camera_grads:
            runs["reached_rows"] = launcher(project.project_gaussians_reached, A, g, args.n, args.device, True)
        rounds = {name: [] for name in runs}
        for _ in range(args.rounds):  # interleaved, median of the rounds' medians
            for name, run in runs.items():
                rounds[name].append(time_call(run, args.device, repeats=args.repeats))
        times = {name: statistics.median(t) for name, t in rounds.items()}
        rows.append({"fraction": fraction, "ms_all": times["all"], "ms_reached": times["reached"],
                     "ratio": times["reached"] / times["all"]}
                    | ({"ms_reached_camera_rows": times["reached_rows"]} if args.camera_grads else
                       {"ms_written": times["written"], "written_over_reached": times["written"] / times["reached"]}))
        print(f"{args.n} Gaussians, {fraction:.0%} reached: every row {rows[-1]['ms_all']:.3f} ms, "
              f"reached rows only {rows[-1]['ms_reached']:.3f} ms ({rows[-1]['ratio']:.2f}x)"
              + (f"; with a camera row per Gaussian {times['reached_rows']:.3f} ms" if args.camera_grads else
                 f"; written out {times['written']:.3f} ms ({times['written'] / times['reached']:.2f}x reached)"))
    result = {"device": args.device, "n": args.n, "sh_degree": 3, "camera_grads": args.camera_grads,
              "repeats": args.repeats, "rounds": args.rounds, "rows": rows}
    if args.device.startswith("cuda"):
        result["gpu"] = wp.get_device(args.device).name
    write_json(f"project_adjoint_{args.device.split(':')[0]}" + ("_camera" if args.camera_grads else ""), result)
    return result


if __name__ == "__main__":
    main()
