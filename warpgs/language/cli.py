"""`warpgs-query`: text / embedding / click queries, 3D delete and extract, and mIoU / mAP on a trained run.

    warpgs-query --model OUT --text "red sphere" [--view NAME] [--threshold 0.4]
    warpgs-query --model OUT --text "red sphere" --delete --extract
    warpgs-query --model OUT --embedding query.npy
    warpgs-query --model OUT --view orbit_000.png --click 40,30
    warpgs-query --model OUT --eval [--split test]

Writes PNGs (relevancy heat map, overlay on the render, mask; delete / extract renders) and a query.json per
query under OUT/queries/<query>/ (or --out), and prints one line per view.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import List, Optional

EXIT_USAGE = 2


def _slug(text: str) -> str:
    return re.sub(r"[^\w.-]+", "_", text.strip().lower()).strip("_") or "query"


def _error(message: str, code: int = EXIT_USAGE) -> int:
    print(f"warpgs-query: error: {message}", file=sys.stderr)
    return code


def _pick_views(trainer, names: List[str], split: str):
    scene = trainer.scene
    if names:
        out = []
        for name in names:
            matches = [i for i, c in enumerate(scene.cameras) if c.name == name or Path(c.name).stem == name]
            if not matches:
                raise ValueError(f"--view: no view named {name!r} (e.g. {', '.join(scene.names[:4])})")
            out.append(scene.view(matches[0], trainer.device))
        return out
    if split == "all":
        return [scene.view(i, trainer.device) for i in range(len(scene))]
    return trainer.eval_views(split)[1]


def _parse_click(text: str):
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--click: expected X,Y in pixels, got {text!r}") from None
    return x, y


def query_main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="warpgs-query", description="Query a trained language field.")
    ap.add_argument("--model", required=True, help="a warpgs-train output folder trained with the language extension")
    ap.add_argument("--text", action="append", default=[], help="text query (repeatable)")
    ap.add_argument("--embedding", action="append", default=[], metavar="FILE.npy",
                    help="query with a given embedding vector (.npy, one row of the feature dimension)")
    ap.add_argument("--click", metavar="X,Y", help="click-to-segment at this pixel of the (first) --view")
    ap.add_argument("--view", action="append", default=[], help="view name or stem (repeatable; default: --split)")
    ap.add_argument("--split", default="test", choices=("test", "train", "all"), help="views when no --view")
    ap.add_argument("--threshold", type=float, help="mask threshold on normalised relevancy (default: the run's, 0.4)")
    ap.add_argument("--click-threshold", type=float, default=0.9, help="cosine threshold for --click (default 0.9)")
    ap.add_argument("--delete", action="store_true", help="also render the views without the selected primitives")
    ap.add_argument("--extract", action="store_true", help="also render only the selected primitives on black")
    ap.add_argument("--select-threshold", type=float, help="3D selection threshold (default: --threshold)")
    ap.add_argument("--eval", action="store_true", help="mIoU / mAP of every label name on the labelled views")
    ap.add_argument("--out", help="output folder (default: MODEL/queries)")
    ap.add_argument("--device", help="cpu, cuda, ... (default: the run's)")
    args = ap.parse_args(argv)
    if not (args.text or args.embedding or args.click or args.eval):
        return _error("give --text, --embedding, --click or --eval")

    import numpy as np
    import torch

    from warpgs.language.query import LanguageField
    from warpgs.language.visualize import mask_overlay, relevancy_overlay, heat_colors, save_png

    try:
        import warpgs.language  # noqa: F401  (registers the extension before the run's config is read)
        field = LanguageField.from_run(args.model, args.device)
        trainer = field.trainer
        views = _pick_views(trainer, args.view, args.split)
    except (ValueError, FileNotFoundError) as e:
        return _error(str(e))
    out_root = Path(args.out) if args.out else Path(args.model) / "queries"
    sel_thr = args.select_threshold if args.select_threshold is not None else args.threshold

    if args.eval:
        from warpgs.language.evaluate import evaluate_language

        split = args.split if not args.view else "views"
        result = evaluate_language(field, views, field.label_names, threshold=args.threshold)
        path = out_root / f"language_metrics_{split}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(result, indent=1))
        print(f"{'label':<20} {'IoU':>6} {'AP':>6} {'n':>3}")
        for name, s in result["per_label"].items():
            print(f"{name:<20} {s['iou']:6.3f} {s['ap']:6.3f} {s['n']:3d}")
        print(f"mIoU {result['miou']:.3f} mAP {result['map']:.3f} over {result['num_queries']} queries -> {path}")

    queries = [(t, t) for t in args.text]
    for p in args.embedding:
        try:
            vec = np.load(p, allow_pickle=False).astype(np.float32).reshape(-1)
        except (OSError, ValueError) as e:
            return _error(f"--embedding {p}: {e}")
        queries.append((Path(p).stem, vec))

    for label, q in queries:
        folder = out_root / _slug(label)
        summary = {"query": label, "views": {}}
        try:
            selection = field.select(q, sel_thr) if (args.delete or args.extract) else None
        except ValueError as e:
            return _error(str(e))
        if selection is not None:
            summary["selected_primitives"] = int(selection.sum())
        for view in views:
            stem = Path(view.name).stem
            r = field.query(view, q, args.threshold)
            rgb = r.rgb.cpu().numpy()
            save_png(folder / f"{stem}_relevancy.png", heat_colors(r.normalised.cpu().numpy()))
            save_png(folder / f"{stem}_overlay.png", relevancy_overlay(rgb, r.normalised.cpu().numpy()))
            save_png(folder / f"{stem}_mask.png", r.mask.cpu().numpy())
            save_png(folder / f"{stem}_mask_overlay.png", mask_overlay(rgb, r.mask.cpu().numpy()))
            entry = {"mask_pixels": int(r.mask.sum()), "max_relevancy": float(r.relevancy.max())}
            labels = getattr(view, "labels", None)
            if isinstance(q, str) and labels is not None:
                ids = [k for k, v in field.label_names.items() if v.lower() == q.strip().lower()]
                if ids:
                    from warpgs.language.evaluate import mask_iou

                    entry["iou"] = mask_iou(r.mask, torch.as_tensor(labels).to(r.mask.device) == ids[0])
            if selection is not None and args.delete:
                save_png(folder / f"{stem}_delete.png", field.delete(view, selection).cpu().numpy())
            if selection is not None and args.extract:
                save_png(folder / f"{stem}_extract.png", field.extract(view, selection).cpu().numpy())
            summary["views"][view.name] = entry
            iou = f" IoU {entry['iou']:.3f}" if "iou" in entry else ""
            print(f"{label!r} {view.name}: {entry['mask_pixels']} px, max relevancy {entry['max_relevancy']:.3f}{iou}")
        (folder / "query.json").write_text(json.dumps(summary, indent=1))
        print(f"-> {folder}")

    if args.click:
        try:
            x, y = _parse_click(args.click)
            view = views[0]
            r = field.click(view, x, y, args.click_threshold)
        except ValueError as e:
            return _error(str(e))
        folder = out_root / f"click_{Path(view.name).stem}_{int(x)}_{int(y)}"
        rgb = r.rgb.cpu().numpy()
        save_png(folder / "similarity.png", heat_colors(r.relevancy.cpu().numpy()))
        save_png(folder / "mask.png", r.mask.cpu().numpy())
        save_png(folder / "mask_overlay.png", mask_overlay(rgb, r.mask.cpu().numpy()))
        feature = field.clicked_feature(view, x, y)
        selection = field.select_like(feature, args.click_threshold)
        if args.delete:
            save_png(folder / "delete.png", field.delete(view, selection).cpu().numpy())
        if args.extract:
            save_png(folder / "extract.png", field.extract(view, selection).cpu().numpy())
        print(f"click ({x:g}, {y:g}) on {view.name}: {int(r.mask.sum())} px, {int(selection.sum())} primitives "
              f"-> {folder}")
    return 0


def main() -> None:
    sys.exit(query_main())


if __name__ == "__main__":
    main()
