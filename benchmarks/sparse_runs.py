"""benchmarks/sparse.py's plan: the protocols, scenes, settings and runs, where a run's file and a scene's prior
go, and whether they are done (a file made with other settings is an error, never reused)."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import ablation
from common import asks_auto_steps, stopped_by_rule
from sparse_tables import SETTINGS, TERMS

GROUPS = {"main": ["baseline", "preset", "full"],
           "terms": TERMS, "paper": ["baseline", *TERMS, "full"], "all": list(SETTINGS)}
FULL_STEPS = ablation.FULL_STEPS["real"]  # the presets' train.steps, on either device (CPU: with a smaller budget)


@dataclass(frozen=True)
class Protocol:
    n_train: int
    downscale: int  # default data.downscale of its scenes
    about: str
    split: str = "llff"  # data.split: "llff" (n_train views spread evenly, every 8th held out) or a light
    # field's "grid" (its 3x3 sub-grid trains, every other view tests; n_train is then the grid's 9)

    @property
    def n_train_arg(self) -> Optional[int]:
        """load_scene's n_train: none for a light field's grid, whose training views are the grid itself."""
        return None if self.split == "grid" else self.n_train

    def data_overrides(self) -> list[str]:
        """The config's data.split and data.n_train for this protocol."""
        n_train = "null" if self.n_train_arg is None else self.n_train_arg
        return [f"data.split={self.split}", f"data.n_train={n_train}"]


PROTOCOLS = {"llff3": Protocol(3, 8, "LLFF, 3 training views, 1/8 resolution (FSGS / DNGaussian)"),
             "m360_24": Protocol(24, 1, "360°, 24 training views (FSGS's Mip-NeRF 360 protocol)"),
             "m360_3": Protocol(3, 1, "360°, 3 training views"),
             "lf3x3": Protocol(9, 4, "light field, a 3x3 camera array spread over the array trains, every other "
                                     "view tests (the Marr-Gestalt paper's protocol)", split="grid")}


@dataclass(frozen=True)
class SceneSpec:
    path: Path
    downscale: int

    @property
    def name(self) -> str:
        return self.path.name


@dataclass(frozen=True)
class Run:
    protocol: str
    scene: SceneSpec
    setting: str
    seed: int

    @property
    def id(self) -> str:
        return f"{self.protocol}_{self.scene.name}_{self.setting}_s{self.seed}"


def parse_scene(spec: str, protocol: Protocol) -> SceneSpec:
    path, _, ds = spec.partition("@")
    if not ds.isdigit() and ds:
        raise SystemExit(f"--scenes: {spec!r}: expected PATH or PATH@DOWNSCALE")
    if not Path(path).is_dir():
        raise SystemExit(f"--scenes: {path} is not a folder")
    if not ds:
        check_llff_images(Path(path), protocol.downscale)
    return SceneSpec(Path(path).resolve(), int(ds) if ds else protocol.downscale)


def check_llff_images(path: Path, downscale: int) -> None:
    """An LLFF folder trimmed to another images_<N> than the protocol's default: an error that says which @N to give
    (NeX's scenes, prepared at 1/2 of their ~1000 px images, hold images_2 only)."""
    llff = (path / "poses_bounds.npy").is_file()
    if not llff or (path / f"images_{downscale}").is_dir() or (path / "images").is_dir():
        return
    have = sorted(p.name for p in path.glob("images_*") if p.is_dir())
    holds = ", ".join(have) or "no image folder"
    raise SystemExit(f"--scenes: {path} has no images_{downscale}/ (nor images/) for the protocol's default "
                     f"1/{downscale}; it holds {holds}: give it as {path}@N for images_N")


def expand_settings(text: str) -> list[str]:
    keys = []
    for part in text.split(","):
        for key in GROUPS.get(part, [part]):
            if key not in SETTINGS:
                raise SystemExit(f"--settings: {key!r} is neither a setting ({', '.join(SETTINGS)}) nor a group "
                                 f"({', '.join(GROUPS)})")
            if key not in keys:
                keys.append(key)
    return keys


def plan(protocol: str, scenes: list[SceneSpec], settings: list[str], seeds: list[int]) -> list[Run]:
    return [Run(protocol, sc, key, seed) for sc in scenes for key in settings for seed in seeds]


def load(scene: SceneSpec, protocol: Protocol, run_sfm: bool = True):
    """The scene as the protocol reads it. A folder of images alone is reconstructed first unless run_sfm is False
    (then it is a SceneError)."""
    from warpgs.data import load_scene

    return load_scene(scene.path, split=protocol.split, n_train=protocol.n_train_arg, downscale=scene.downscale,
                      run_sfm_if_needed=run_sfm)


def protocol_for(name: str, n_train: Optional[int] = None) -> tuple[Protocol, str]:
    """(the protocol, the tag its run files and priors are named by): `name`'s, or its split rule with n_train
    training views (tag <name>_n<N>); a light field's grid takes no other count."""
    protocol = PROTOCOLS[name]
    if n_train is None:
        return protocol, name
    if n_train < 1:
        raise SystemExit(f"--n-train: expected at least 1, got {n_train}")
    if protocol.split == "grid":
        raise SystemExit(f"--n-train: protocol {name} trains on its light field's 3x3 grid")
    about = f"{protocol.about}, with {n_train} training views"
    return Protocol(n_train, protocol.downscale, about), f"{name}_n{n_train}"


def prior_folder(out: Path, protocol: str, scene: SceneSpec) -> Path:
    return out / "priors" / f"{protocol}_{scene.name}"


def needs_prior(run: Run, user_overrides=()) -> bool:
    _, preset, overrides, _ = SETTINGS[run.setting]
    return ablation.uses_prior(preset, [*user_overrides, *overrides])


def prior_done(out: Path, protocol: str, scene: SceneSpec) -> bool:
    """Whether the scene's prior is made. One made at another downscale (the folder is named by protocol and scene
    only, and the loader would silently resize it) is an error."""
    f = prior_folder(out, protocol, scene) / "prior.json"
    if not f.is_file():
        return False
    made = json.loads(f.read_text()).get("downscale", scene.downscale)  # files from before it was recorded
    if made != scene.downscale:
        raise SystemExit(f"{f}: the prior was made at downscale {made}, this plan reads {scene.name} at "
                         f"{scene.downscale}: give another --out, or delete {f.parent}")
    return True


def run_steps(args) -> int:
    return args.steps or FULL_STEPS


def run_budget(args) -> Optional[int]:
    return args.budget or (None if args.device.startswith("cuda") else ablation.CPU_BUDGET)


def run_file(out: Path, run: Run) -> Path:
    return out / "runs" / f"{run.id}.json"


def run_done(args, run: Run) -> bool:
    """Whether the run's file exists (made with this plan's settings, see read_run)."""
    return read_run(args, run) is not None


def read_run(args, run: Run) -> Optional[dict]:
    """The run's file (None when there is none). Its name leaves out the steps, the budget and the downscale, so a
    file made with others (a CPU smoke wave, then the real one into the same --out) is an error, never reused or
    tabulated."""
    f = run_file(Path(args.out), run)
    if not f.is_file():
        return None
    recorded = json.loads(f.read_text())
    wanted = {"steps": run_steps(args), "budget": run_budget(args), "downscale": run.scene.downscale}
    differ = {k: (recorded.get(k), v) for k, v in wanted.items() if recorded.get(k) != v}
    if (stopped_by_rule(recorded) and asks_auto_steps(args.overrides)
            and recorded.get("steps", wanted["steps"] + 1) <= wanted["steps"]):
        differ.pop("steps", None)  # train.steps=auto ends where its rule says, within the plan's steps
    if differ:
        raise SystemExit(f"{f}: made with " + ", ".join(f"{k} {a}" for k, (a, _) in differ.items())
                         + "; this plan asks for " + ", ".join(f"{k} {b}" for k, (_, b) in differ.items())
                         + ": give another --out (or the same --steps/--budget/--device/@downscale), or delete it")
    return recorded
