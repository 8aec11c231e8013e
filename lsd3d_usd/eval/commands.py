"""`lsd3d-usd eval`: seen vs novel views, geometry, temporal consistency of a scene."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lsd3d_usd import configtree as ct
from lsd3d_usd.cliutil import check_output_path
from lsd3d_usd.eval.options import EvalConfig
from lsd3d_usd.views.commands import check_deferred


def _eval(args) -> int:
    got = ct.command_config(args, EvalConfig, needs={"scene": "eval: give the SCENE folder"})
    if got is None:
        return 0
    cfg, explicit = got
    check_deferred(cfg.deferred, explicit)
    if args.json:   # checked now, not after the whole evaluation
        check_output_path(args.json, "--json", what="metrics file")
    # heavy (torch, the renderer, EfficientNet): once an evaluation is asked for
    from lsd3d_usd.eval.evaluate import EvalOptions, evaluate
    o = EvalOptions(scene=Path(args.scene), cfg=cfg, out_dir=Path(args.out) if args.out else None,
                    progress=not args.no_progress and sys.stderr.isatty(),
                    log=lambda *a: print(*a, file=sys.stderr))
    res = evaluate(o)
    if args.json:
        # local import: not loaded for --help
        from lsd3d_usd.eval.report import write_json
        write_json(Path(args.json), res.to_json())
    fds = res.distances
    fd = fds.seen_vs_novel
    per = ", ".join(f"{b} m {v['value']:.1f}" for b, v in fd.per_bin.items())
    g = res.geometry.seen["all"]
    print(f"fd_effnet_lite0 seen vs novel: {fd.overall['value']:.2f} (per bin: {per})")
    if fds.seen_vs_heldout_lane is not None:
        print(f"fd_effnet_lite0 seen vs other on-lane views: "
              f"{fds.seen_vs_heldout_lane['value']:.2f}")
    if fds.prior_baseline is not None:
        pb = fds.prior_baseline
        rows = ", ".join(f"{b} m {pb['scene_novel_over_content'][b]:.2f} / {v:.2f}"
                         for b, v in pb["prior_novel_over_content"].items())
        print(f"fd_effnet_lite0 novel over content change, scene / the prior's own images: {rows}")
    _print_elevated(res.novel_elevated)
    _print_off_path(res.novel_off_path)
    if fds.vs_reference is not None:
        r = fds.vs_reference
        print(f"fd_effnet_lite0 vs reference: seen {r['seen']['value']:.2f}, novel {r['novel']['value']:.2f}")
    mv, t = res.multiview, res.temporal
    print(f"geometry (seen): depth err median {_pct(g['depth_rel_err_median'])}, normal err median "
          f"{g['normal_err_deg_median']} deg, coverage {_pct(g['coverage'])}")
    print(f"multi-view depth err median {_pct(mv.median)}; temporal warp err {t['warp_err']} "
          f"(naive {t['naive_err']})")
    if res.deferred is not None:
        dr = res.deferred
        d, td = dr.provenance, dr.temporal
        print(f"deferred (prior {d['prior']}, T {d['strength']}, N {d['steps']}, "
              f"{d.get('s_per_frame', 0):.3f} s/frame): fd seen vs novel "
              f"{dr.seen_vs_novel.overall['value']:.2f}; fd vs the prior's images raw "
              f"{dr.vs_prior_raw['value']:.2f} -> deferred "
              f"{dr.vs_prior_deferred['value']:.2f}; temporal warp err raw "
              f"{t['warp_err']} -> deferred {td['warp_err']}")
    vs = (res.seams or {}).get("vs_reference")
    if vs and vs.get("difference_db") is not None:
        print(f"seams: matched drop {vs['scene_db']} dB, the reference {vs['reference_db']} dB: "
              f"chunk-wise adds {vs['difference_db']} dB (95 % interval {vs['ci95_db']})")
    for u in res.unavailable:
        print(f"{u['metric']}: unavailable: {u['reason']}")
    for w in res.warnings:
        print(f"warning: {w}", file=sys.stderr)
    print(f"report: {res.files['html']}")
    if args.json:
        print(f"json: {args.json}")
    return 0


def _print_elevated(ne: dict) -> None:
    parts = []
    for group, r in ne.items():
        if group == "heldout_lane":
            continue
        psnr = r.get("psnr_db", {}).get("mean")
        parts.append(f"{group if group == 'overview' else group + ' m'} "
                     + (f"PSNR {psnr:.2f} dB, " if psnr is not None else "") + f"fd {r['fd']:.1f}"
                     + (f" ({r['fd_over_prior']:.2f}x the prior's ratio)" if "fd_over_prior" in r else ""))
    if parts:
        lane = ne.get("heldout_lane", {}).get("psnr_db", {}).get("mean")
        print("elevated views: " + "; ".join(parts)
              + (f" (held-out lane views PSNR {lane:.2f} dB)" if lane is not None else ""))


def _print_off_path(op: dict) -> None:
    psnr, ratio = op.get("psnr_db_per_bin"), op.get("fd_over_prior_per_bin") or {}
    if not op:
        return
    parts = [f"{k} " + (f"PSNR {psnr[k]:.2f} dB" if psnr and psnr[k] is not None else "")
             + (f", fd {ratio[k]:.2f}x the prior's" if k in ratio else "")
             for k in op["bins"]]
    print(f"off-path views ({op['stations']} per bin): " + "; ".join(parts))
    cls = op.get("psnr_db_per_class")
    if cls:
        print("off-path PSNR per class: " + ", ".join(
            f"{c} {v:.2f} dB" for c, v in cls.items() if v is not None))


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
                    " files (--weights) and are otherwise reported as unavailable. Every setting "
                    "has a key (--list-options) for --config FILE.toml and --set KEY=VALUE. See "
                    "docs/eval.md.")
    p.add_argument("scene", nargs="?", help="scene folder, or its root layer scene.usda")
    p.add_argument("--json", metavar="FILE", help="also write the metrics JSON here "
                                                   "(always written to SCENE/eval/eval.json)")
    p.add_argument("-o", "--out", metavar="DIR", help="report folder (default SCENE/eval)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    ct.add_tree_options(p, "eval")
    ct.add_arguments(p, EvalConfig, titles={"deferred": "deferred rendering (docs/render.md): "
                                                        "the seen, novel and trajectory views "
                                                        "also deferred, figures beside the raw "
                                                        "ones"})
    p.set_defaults(func=_eval, compiles_kernels=True)
