"""`lsd3d-usd eval`: seen vs novel views, geometry, temporal consistency of a scene."""
from __future__ import annotations

import argparse
import sys

from lsd3d_usd.cliutil import parse_size
from lsd3d_usd.views.commands import add_deferred_arguments, check_deferred_args


def _bins(text: str) -> tuple[float, ...]:
    from lsd3d_usd.errors import InputError
    try:
        vals = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise InputError(f"--bins {text!r}: expected comma-separated metres, e.g. 0.5,1,2,4,8") from None
    if not vals:
        raise InputError("--bins: give at least one distance")
    return vals


def _eval(args) -> int:
    from pathlib import Path

    from lsd3d_usd.eval.evaluate import EvalOptions, evaluate
    o = EvalOptions(
        scene=Path(args.scene), out_dir=Path(args.out) if args.out else None, run=args.run,
        reference=Path(args.reference) if args.reference else None,
        weights=Path(args.weights) if args.weights else None, n_seen=args.seen, n_heldout=args.heldout,
        per_bin=args.per_bin, bins=_bins(args.bins), resolution=parse_size(args.resolution),
        seed=args.seed, frames=args.frames, step_m=args.step, tonemap=args.tonemap,
        exposure=args.exposure, max_reference=args.max_reference,
        progress=not args.no_progress and sys.stderr.isatty(),
        log=lambda *a: print(*a, file=sys.stderr), deferred=args.deferred,
        deferred_strength=args.deferred_strength, deferred_steps=args.deferred_steps,
        deferred_prior=args.deferred_prior,
        deferred_controlnet=Path(args.deferred_controlnet) if args.deferred_controlnet else None,
        deferred_device=args.deferred_device, deferred_seed=args.deferred_seed,
        prior_baseline=args.prior_baseline,
        seams_reference=Path(args.seams_reference) if args.seams_reference else None)
    check_deferred_args(args)
    res = evaluate(o)
    if args.json:
        from lsd3d_usd.eval.report import write_json
        write_json(Path(args.json), res)
    fd = res["fd_effnet_lite0"]["seen_vs_novel"]
    per = ", ".join(f"{b} m {v['value']:.1f}" for b, v in fd["per_bin"].items())
    g = res["geometry"]["seen"]["all"]
    print(f"fd_effnet_lite0 seen vs novel: {fd['overall']['value']:.2f} (per bin: {per})")
    if "seen_vs_heldout_lane" in res["fd_effnet_lite0"]:
        print(f"fd_effnet_lite0 seen vs other on-lane views: "
              f"{res['fd_effnet_lite0']['seen_vs_heldout_lane']['value']:.2f}")
    if "prior_baseline" in res["fd_effnet_lite0"]:
        pb = res["fd_effnet_lite0"]["prior_baseline"]
        rows = ", ".join(f"{b} m {pb['scene_novel_over_content'][b]:.2f} / {v:.2f}"
                         for b, v in pb["prior_novel_over_content"].items())
        print(f"fd_effnet_lite0 novel over content change, scene / the prior's own images: {rows}")
    if "vs_reference" in res["fd_effnet_lite0"]:
        r = res["fd_effnet_lite0"]["vs_reference"]
        print(f"fd_effnet_lite0 vs reference: seen {r['seen']['value']:.2f}, novel {r['novel']['value']:.2f}")
    mv, t = res["multiview_depth_err"], res["temporal_warp_err"]
    print(f"geometry (seen): depth err median {_pct(g['depth_rel_err_median'])}, normal err median "
          f"{g['normal_err_deg_median']} deg, coverage {_pct(g['coverage'])}")
    print(f"multi-view depth err median {_pct(mv['median'])}; temporal warp err {t['warp_err']} "
          f"(naive {t['naive_err']})")
    if "deferred" in res:
        d = res["deferred"]
        dfd, td = d["fd_effnet_lite0"], d["temporal_warp_err"]
        print(f"deferred (prior {d['prior']}, T {d['strength']}, N {d['steps']}, "
              f"{d.get('s_per_frame', 0):.3f} s/frame): fd seen vs novel "
              f"{dfd['seen_vs_novel']['overall']['value']:.2f}; fd vs the prior's images raw "
              f"{dfd['vs_prior_target']['raw']['value']:.2f} -> deferred "
              f"{dfd['vs_prior_target']['deferred']['value']:.2f}; temporal warp err raw "
              f"{t['warp_err']} -> deferred {td['warp_err']}")
    vs = (res.get("seams") or {}).get("vs_reference")
    if vs and vs.get("difference_db") is not None:
        print(f"seams: matched drop {vs['scene_db']} dB, the reference {vs['reference_db']} dB: "
              f"chunk-wise adds {vs['difference_db']} dB (95 % interval {vs['ci95_db']})")
    for u in res["unavailable"]:
        print(f"{u['metric']}: unavailable: {u['reason']}")
    for w in res["warnings"]:
        print(f"warning: {w}", file=sys.stderr)
    print(f"report: {res['files']['html']}")
    if args.json:
        print(f"json: {args.json}")
    return 0


def _pct(x) -> str:
    return "n/a" if x is None else f"{100 * x:.2f} %"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "eval", help="evaluate a scene: seen vs novel views (Fréchet distance), geometry, temporal",
        description="Render the scene's composed stage (all unmuted layers: initial surfels + GGDS "
                    "overs, env map behind) from the cameras the newest GGDS run trained on (seen) "
                    "and from novel cameras displaced from them by increasing distances, then report "
                    "the Fréchet distance of EfficientNet-Lite0 features (fd_effnet_lite0, never "
                    "called FID) seen vs novel per distance bin and against --reference images, "
                    "depth/normal agreement with the proxy per class, multi-view depth consistency, "
                    "and frame-to-frame warp error along a lane. Writes SCENE/eval/report.html with "
                    "PNGs and eval.json. Inception FID, FD-DINOv2, CLIP score and FVD need local weight"
                    " files (--weights) and are otherwise reported as unavailable. See docs/eval.md.")
    p.add_argument("scene", help="scene folder, or its root layer scene.usda")
    p.add_argument("--json", metavar="FILE", help="also write the metrics JSON here "
                                                   "(always written to SCENE/eval/eval.json)")
    p.add_argument("--reference", metavar="DIR",
                   help="folder of reference images (png/jpg/...; at least 2) to compare against")
    p.add_argument("--weights", metavar="DIR",
                   help="folder of local weight files for Inception FID / FD-DINOv2 / CLIP score / FVD "
                        "(expected names in docs/eval.md); nothing is downloaded")
    p.add_argument("--run", metavar="NAME", help="GGDS run whose training cameras are the seen views "
                                                 "(default: the newest unmuted run)")
    p.add_argument("--seen", type=int, default=16, help="seen views to render (default 16)")
    p.add_argument("--heldout", type=int, default=None,
                   help="fresh on-lane views (not trained on) rendered as the FD reference for a "
                        "change of content (default: as many as --seen; 0 = none)")
    p.add_argument("--per-bin", type=int, default=16, help="novel views per distance bin (default 16)")
    p.add_argument("--bins", default="0.5,1,2,4,8",
                   help="novel-view distances from the training cameras in metres (default 0.5,1,2,4,8)")
    p.add_argument("--resolution", default="320x180", help="render size WxH (default 320x180)")
    p.add_argument("--frames", type=int, default=24, help="trajectory frames for the temporal check "
                                                          "(default 24)")
    p.add_argument("--step", type=float, default=0.5, help="trajectory spacing in metres (default 0.5)")
    p.add_argument("--seed", type=int, default=0, help="seed of view selection and novel offsets")
    p.add_argument("--tonemap", default="clamp", choices=("clamp", "aces", "reinhard"),
                   help="display encoding before features (default clamp: what GGDS's prior sees)")
    p.add_argument("--exposure", type=float, default=0.0, help="exposure in stops before tone mapping")
    p.add_argument("--max-reference", type=int, default=500, help="use at most this many reference images")
    p.add_argument("--prior-baseline", action=argparse.BooleanOptionalAction, default=None,
                   help="also render the scene's prior at t = 1 from the same seen, novel and "
                        "held-out views: the Fréchet distances a scene reproducing its prior "
                        "exactly would give (default: on for the procedural prior, off for a "
                        "diffusion prior, which is slow on the CPU)")
    p.add_argument("--seams-reference", metavar="SCENE",
                   help="a scene of the same layout without chunk seams (generated with "
                        "--regions scene and the same seed and settings): rendered from the "
                        "held-out views, it gives what the chunk-wise optimisation adds to the "
                        "seam drop (seams.vs_reference in the JSON)")
    p.add_argument("-o", "--out", metavar="DIR", help="report folder (default SCENE/eval)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_deferred_arguments(p, "the seen, novel and trajectory views (figures beside the raw ones)")
    p.set_defaults(func=_eval, compiles_kernels=True)
