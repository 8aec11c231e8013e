"""The evaluation report beside the scene: eval.json, report.html (self-contained apart from
the PNGs next to it, referenced relatively) and PNGs: contact sheet (seen views and their
novel views per distance bin), Fréchet distance by distance, a geometry panel, the temporal
path, and the GGDS loss curve copied from SCENE/ggds/<run>/loss.png. Every file is written
atomically (temp + rename)."""
from __future__ import annotations

import html
import io
import json
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np

from lsd3d_usd import scene as S
from lsd3d_usd.eval.geometry import surfel_depth, unit
from lsd3d_usd.eval.result import EvalResult


def _save_fig(fig, path: Path) -> Path:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    return S.atomic_write_bytes(path, buf.getvalue())


def write_json(path: Path, data: dict) -> Path:
    return S.atomic_write_bytes(path, (json.dumps(data, indent=2, default=str) + "\n").encode())


def _plt():
    matplotlib.use("Agg")
    return plt


def contact_sheet(path: Path, seen_img, novel_img, novel, bins, rows: int = 4) -> Path:
    plt = _plt()
    rows = min(rows, len(seen_img))
    cols = 1 + len(bins)
    h, w = seen_img[0].shape[:2]
    fig, ax = plt.subplots(rows, cols, figsize=(2.2 * cols, 2.2 * rows * h / w + 0.4), squeeze=False)
    for r in range(rows):
        ax[r, 0].imshow(seen_img[r])
        for c, b in enumerate(bins):
            k = next((i for i, nv in enumerate(novel) if nv.bin_m == b and nv.source == r), None)
            if k is not None:
                ax[r, c + 1].imshow(novel_img[k])
        for a in ax[r]:
            a.set_xticks([]); a.set_yticks([])
    ax[0, 0].set_title("seen (trained)", fontsize=9)
    for c, b in enumerate(bins):
        ax[0, c + 1].set_title(f"novel {b:g} m", fontsize=9)
    fig.tight_layout(pad=0.3)
    return _save_fig(fig, path)


def elevated_sheet(path: Path, views, images, cols: int = 4) -> Path:
    """The elevated views: one row per height (and one of the Overview cameras)."""
    plt = _plt()
    groups = list(dict.fromkeys(v.group for v in views))
    rows = [[i for i, v in enumerate(views) if v.group == g][:cols] for g in groups]
    cols = max(len(r) for r in rows)
    h, w = images[0].shape[:2]
    fig, ax = plt.subplots(len(rows), cols, figsize=(2.2 * cols, 2.2 * len(rows) * h / w + 0.4),
                           squeeze=False)
    for r, (g, idx) in enumerate(zip(groups, rows)):
        for c in range(cols):
            a = ax[r, c]
            a.set_xticks([]); a.set_yticks([])
            if c < len(idx):
                v = views[idx[c]]
                a.imshow(images[idx[c]])
                a.set_title(v.name if g == "overview" else f"{v.height_m:g} m, {v.pitch_deg:.0f}° down",
                            fontsize=8)
            else:
                a.axis("off")
        ax[r, 0].set_ylabel(g if g == "overview" else f"{g} m", fontsize=9)
    fig.tight_layout(pad=0.3)
    return _save_fig(fig, path)


def off_path_sheet(path: Path, off, images, prior_images, cols: int = 3) -> Path:
    """The off-path views: one row per bin, for each of its first ``cols`` stations the
    prior's image of the camera (when the prior baseline made one) beside the surfels'. One
    mosaic in one axes (tens of subplots cost seconds)."""
    plt = _plt()
    keys = [k for k, idx in off.bins.items() if idx]
    n = min(cols, max(len(off.bins[k]) for k in keys))
    h, w = images[0].shape[:2]
    gap = 3
    sources = ([prior_images] if prior_images else []) + [images]
    tiles = len(sources) * n
    mosaic = np.ones((len(keys) * (h + gap) - gap, tiles * (w + gap) - gap, 3), np.float32)
    for r, k in enumerate(keys):
        for c in range(tiles):
            s = c // len(sources)
            if s < len(off.bins[k]):
                im = sources[c % len(sources)][off.bins[k][s]]
                mosaic[r * (h + gap):r * (h + gap) + h, c * (w + gap):c * (w + gap) + w] = im
    fig_w = 1.4 * tiles + 1.0
    fig, ax = plt.subplots(figsize=(fig_w, 1.4 * len(keys) * h / w + 0.5))
    ax.imshow(np.clip(mosaic, 0, 1))
    ax.set_yticks([r * (h + gap) + h / 2 for r in range(len(keys))])
    ax.set_yticklabels(keys, fontsize=7)
    names = ["prior", "surfels"] if prior_images else ["surfels"]
    ax.set_xticks([c * (w + gap) + w / 2 for c in range(tiles)])
    ax.set_xticklabels([names[c % len(names)] for c in range(tiles)], fontsize=7)
    ax.xaxis.tick_top()
    # room for the bin keys on the left (tight_layout clips them beside an image axes)
    fig.subplots_adjust(left=0.95 / fig_w, right=0.99, top=0.95, bottom=0.01)
    return _save_fig(fig, path)


def fd_plot(path: Path, result: EvalResult) -> Path:
    plt = _plt()
    fd = result.distances
    bins = result.bins_m
    ys = [fd.seen_vs_novel.per_bin[f"{b:g}"]["value"] for b in bins]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.0))
    ax[0].plot(bins, ys, "o-", label="seen vs novel (per bin)")
    if fd.seen_vs_heldout_lane is not None:
        ax[0].axhline(fd.seen_vs_heldout_lane["value"], color="gray", ls="--",
                      label="seen vs other on-lane views (content change)")
    if fd.prior_baseline is not None:
        pb = fd.prior_baseline
        ax[0].plot(bins, [pb["seen_vs_novel"]["per_bin"][f"{b:g}"]["value"] for b in bins], "^:",
                   color="C1", label="the prior's own images: seen vs novel")
        ax[0].axhline(pb["seen_vs_heldout_lane"]["value"], color="C1", ls=":",
                      label="the prior's own images: content change")
    if fd.vs_reference is not None:
        ax[0].plot(bins, [fd.vs_reference["novel_per_bin"][f"{b:g}"]["value"] for b in bins], "s-",
                   label="novel vs reference")
        ax[0].axhline(fd.vs_reference["seen"]["value"], color="C2", ls=":", label="seen vs reference")
    ax[0].set_xlabel("novel view distance from training camera (m)")
    ax[0].set_ylabel("FD (EfficientNet-Lite0)"); ax[0].set_ylim(bottom=0); ax[0].legend(fontsize=7)
    mv = result.multiview.per_bin
    ax[1].plot(bins, [100 * (mv[f"{b:g}"]["median"] or np.nan) for b in bins], "o-")
    ax[1].set_xlabel("distance (m)"); ax[1].set_ylim(bottom=0)
    ax[1].set_ylabel("median reprojected depth err (%)")
    for a in ax:
        a.set_xscale("log", base=2); a.set_xticks(bins); a.set_xticklabels([f"{b:g}" for b in bins])
        a.minorticks_off()
    fig.tight_layout()
    return _save_fig(fig, path)


def geometry_panel(path: Path, img, frame, gbuf) -> Path:
    plt = _plt()
    d_s = surfel_depth(frame)
    ok = gbuf.mask & (frame["alpha"] > 0.5)
    d_p = np.where(gbuf.mask, gbuf.depth, np.nan)
    rel = np.where(ok, np.abs(d_s - d_p) / np.where(gbuf.mask, gbuf.depth, 1.0), np.nan)
    n_s = unit(frame["normal_world"].astype(np.float64))
    n_p = gbuf.normal.astype(np.float64)
    ang = np.degrees(np.arccos(np.clip(np.abs(np.sum(n_s * n_p, -1)), 0, 1)))
    ang = np.where(ok, ang, np.nan)
    vmax = np.nanpercentile(d_p, 95) if np.isfinite(d_p).any() else 1.0
    panels = [(img, "render", {}), (np.where(frame["alpha"] > 0.5, d_s, np.nan), "surfel depth (m)",
                                    dict(cmap="viridis", vmin=0, vmax=vmax)),
              (d_p, "proxy depth (m)", dict(cmap="viridis", vmin=0, vmax=vmax)),
              (100 * rel, "|depth err| (%)", dict(cmap="magma", vmin=0, vmax=5)),
              (ang, "normal err (deg)", dict(cmap="magma", vmin=0, vmax=30))]
    fig, ax = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 2.3))
    for a, (im, title, kw) in zip(ax, panels):
        m = a.imshow(im, **kw)
        a.set_title(title, fontsize=9); a.set_xticks([]); a.set_yticks([])
        if kw:
            fig.colorbar(m, ax=a, fraction=0.03)
    fig.tight_layout(pad=0.3)
    return _save_fig(fig, path)


def temporal_panel(path: Path, traj_img, temporal: dict, deferred: dict | None = None) -> Path:
    plt = _plt()
    picks = sorted({0, len(traj_img) // 2, len(traj_img) - 1})
    fig, ax = plt.subplots(1, len(picks) + 1, figsize=(3.2 * (len(picks) + 1), 2.3))
    for a, i in zip(ax, picks):
        a.imshow(traj_img[i]); a.set_title(f"frame {i}", fontsize=9); a.set_xticks([]); a.set_yticks([])
    curves = [("warp err", temporal)] + ([("deferred", deferred)] if deferred else [])
    for label, tm in curves:
        per = [np.nan if e is None else e for e in tm["per_pair"]]
        ax[-1].plot(range(1, len(per) + 1), per, ".-", label=label)
    if deferred:
        ax[-1].legend(fontsize=7)
    ax[-1].set_xlabel("frame"); ax[-1].set_ylabel("mean |Δ sRGB|"); ax[-1].set_ylim(bottom=0)
    fig.tight_layout(pad=0.3)
    return _save_fig(fig, path)


def deferred_sheet(path: Path, seen_img, deferred, traj_img, rows: int = 3) -> Path:
    """Raw | deferred | the prior's own image (t = 1) for a few seen views, then raw | deferred
    for trajectory frames."""
    plt = _plt()
    n_seen = min(rows, len(seen_img))
    picks = sorted({0, len(traj_img) // 2, len(traj_img) - 1})
    panels = [(seen_img[i], deferred.images["seen"][i], deferred.targets["seen"][i], f"seen {i}")
              for i in range(n_seen)]
    panels += [(traj_img[i], deferred.images["traj"][i], None, f"trajectory frame {i}") for i in picks]
    h, w = seen_img[0].shape[:2]
    fig, ax = plt.subplots(len(panels), 3, figsize=(9.6, 3.2 * h / w * len(panels) + 0.4), squeeze=False)
    for r, (raw, dfd, tgt, label) in enumerate(panels):
        for c, im in enumerate((raw, dfd, tgt)):
            if im is not None:
                ax[r, c].imshow(im)
            else:
                ax[r, c].axis("off")
            ax[r, c].set_xticks([]); ax[r, c].set_yticks([])
        ax[r, 0].set_ylabel(label, fontsize=8)
    for c, title in enumerate(("raw", "deferred", "prior's image (t = 1)")):
        ax[0, c].set_title(title, fontsize=9)
    fig.tight_layout(pad=0.3)
    return _save_fig(fig, path)


# ------------------------------------------------------------------ HTML
def _fmt(x, pct=False, digits=3):
    if x is None:
        return "–"
    if pct:
        return f"{100 * x:.2f} %"
    return f"{x:.{digits}f}" if isinstance(x, float) else html.escape(str(x))


def _seams_html(result: EvalResult) -> str:
    s = result.seams
    if not s:
        return "<p>not measured (see Not computed)</p>"
    rows = []
    for k in ("border", "interior"):
        v = s[k]
        rows.append([f"{k} ({'≤' if k == 'border' else '>'} {s['band_m']:g} m from a chunk border)",
                     "–" if v["psnr_db"] is None else f"{v['psnr_db']:.2f}",
                     "–" if v["coverage"] is None else f"{100 * v['coverage']:.2f} %",
                     "–" if v["depth_rel_err"] is None else f"{100 * v['depth_rel_err']:.2f} %",
                     "–" if v["normal_err_deg"] is None else f"{v['normal_err_deg']:.2f}°",
                     f"{s['pixels'][k]:,}"])
    drop = "" if s["psnr_drop_db"] is None else f"<p>PSNR drop at the borders: {s['psnr_drop_db']:.2f} dB"
    if drop and s.get("psnr_drop_class_matched_db") is not None:
        drop += (f"; class-matched (interiors weighted to the border band's semantic mix): "
                 f"{s['psnr_drop_class_matched_db']:.2f} dB")
    if drop and s.get("psnr_drop_matched_db") is not None:
        ci = s.get("psnr_drop_matched_ci95_db")
        drop += (f"; class and distance matched: {s['psnr_drop_matched_db']:.2f} dB"
                 + (f" (95 % interval over the views {ci[0]:.2f} to {ci[1]:.2f} dB)" if ci else ""))
    drop += "</p>" if drop else ""
    vs = s.get("vs_reference")
    if vs and vs.get("difference_db") is not None:
        ci = vs.get("ci95_db")
        drop += (f"<p>Against {html.escape(vs['scene'])} (the same layout without chunk seams, "
                 f"from the same views): its matched drop {vs['reference_db']:.2f} dB, so the "
                 f"chunk-wise optimisation adds {vs['difference_db']:.2f} dB"
                 + (f" (95 % interval {ci[0]:.2f} to {ci[1]:.2f} dB)" if ci else "") + "</p>")
    return _table(["pixels", "PSNR vs prior (dB)", "coverage", "depth err", "normal err",
                   "pixels"], rows) + drop


def _elevated_html(result: EvalResult) -> str:
    ne = result.novel_elevated
    groups = [g for g in ne if g != "heldout_lane"]
    if not groups:
        return "<p>no elevated views (--per-height 0 and no Overview cameras)</p>"

    def ps(row, k):
        return _fmt(row.get("psnr_db", {}).get(k), digits=2)
    rows = []
    for g in groups:
        r = ne[g]
        rows.append([f"{g} m" if g != "overview" else "Overview cameras", r["views"],
                     _fmt(r.get("height_m_median"), digits=1), _fmt(r.get("pitch_deg_median"), digits=1),
                     ps(r, "mean"), ps(r, "min"), _fmt(r["fd"]), _fmt(r.get("fd_over_content")),
                     _fmt(r.get("prior_fd_over_content")), _fmt(r.get("fd_over_prior"))])
    if "heldout_lane" in ne:
        h = ne["heldout_lane"]
        rows.append(["held-out lane views (for scale)", h["psnr_db"].get("views", ""), "", "",
                     ps(h, "mean"), ps(h, "min"), "", "", "", ""])
    out = ("<p>Cameras 5-30 m above a lane point they look down at (and the scene's Overview "
           "cameras): PSNR of the render against the GGDS run's held-out target of the same "
           "view, FD of their features against the seen views', over the content change "
           "(seen vs other on-lane views), for the scene and for the prior's own images of "
           "the same cameras.</p>"
           + _table(["height", "views", "height (median m)", "pitch (median °)",
                     "PSNR vs prior (dB, mean)", "PSNR (min)", "FD vs seen", "FD / content",
                     "prior's FD / content", "scene / prior"], rows))
    per_cam = (ne.get("overview") or {}).get("psnr_db_per_camera")
    if per_cam:
        out += "<h3>Overview cameras</h3>" + _table(
            ["camera", "PSNR vs prior (dB)"], [[html.escape(k), _fmt(v, digits=2)]
                                               for k, v in per_cam.items()])
    return out


def _off_path_html(result: EvalResult) -> str:
    op = result.novel_off_path
    if not op:
        return "<p>no off-path views (--off-path-per-bin 0)</p>"
    psnr = op.get("psnr_db_per_bin", {})
    rows = [[html.escape(k), f"{b['lateral_m']:g}", f"{b['height_m']:g}", f"{b['yaw_deg']:g}",
             _fmt(psnr.get(k), digits=2), _fmt(op.get("fd_per_bin", {}).get(k), digits=1),
             _fmt(op.get("fd_over_content_per_bin", {}).get(k)),
             _fmt(op.get("prior_fd_over_content_per_bin", {}).get(k)),
             _fmt(op.get("fd_over_prior_per_bin", {}).get(k)),
             _fmt(op.get("fd_vs_prior_images_per_bin", {}).get(k), digits=1)]
            for k, b in op["bins"].items()]
    return (f"<p>{op['stations']} stations on the drivable lanes ({op['regions']} region(s)), "
            f"one camera per bin at each, {html.escape(op['rig_camera'])} intrinsics, each bin "
            "changing one thing from the on-path camera (lane centre, 1.6 m, along the lane): "
            "PSNR against the run's target of the same camera, FD of the bin's features against "
            "the seen views' over the content change, for the scene and the prior's own images "
            "of the same cameras, and their ratio.</p>"
            + _table(["bin", "lateral (m)", "height (m)", "yaw (°)", "PSNR vs prior (dB)",
                      "FD vs seen", "FD / content", "prior's FD / content", "scene / prior",
                      "FD vs the prior's images"], rows))


def _class_html(result: EvalResult) -> str:
    """PSNR per semantic class of every family (the run's targets)."""
    fams = [("seen", result.seen_views)]
    fams += [(f"novel {b} m", v) for b, v in result.novel_views.items()]
    fams += [("held-out lane" if g == "heldout_lane" else
              ("Overview cameras" if g == "overview" else f"elevated {g} m"), v)
             for g, v in result.novel_elevated.items()]
    op = result.novel_off_path
    if op.get("psnr_db_per_class"):
        fams.append(("off-path (all bins)", {"psnr_db": {"mean": None},
                                              "psnr_db_per_class": op["psnr_db_per_class"]}))
    fams.append(("trajectory", result.temporal))
    fams = [(n, v) for n, v in fams if v.get("psnr_db_per_class")]
    if not fams:
        return "<p>not measured (see Not computed)</p>"
    classes = list(fams[0][1]["psnr_db_per_class"])
    rows = [[html.escape(n), _fmt((v.get("psnr_db") or {}).get("mean"), digits=2)]
            + [_fmt(v["psnr_db_per_class"].get(c), digits=2) for c in classes] for n, v in fams]
    return ("<p>PSNR (dB) of the renders against the GGDS run's targets of the same views, "
            "over the pixels of each class in the proxy G-buffer the prior conditioned on.</p>"
            + _table(["views", "all (mean of views)"] + classes, rows))


def _table(header, rows) -> str:
    th = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{th}</tr>{body}</table>"


def html_report(result: EvalResult, images: dict) -> str:
    fd = result.distances
    bins = [f"{b:g}" for b in result.bins_m]
    mv = result.multiview
    nv = result.novel_views
    rows = [["seen vs all novel", _fmt(fd.seen_vs_novel.overall["value"]), "", "",
             _fmt(mv.median, pct=True), _fmt(mv.frac_over_5pct, pct=True)]]
    for b in bins:
        m = mv.per_bin[b]
        rows.append([f"seen vs novel {b} m", _fmt(fd.seen_vs_novel.per_bin[b]["value"]),
                     _fmt(nv[b].get("nearest_train_m_median"), digits=2),
                     _fmt(nv[b].get("abs_yaw_deg_median"), digits=1), _fmt(m["median"], pct=True),
                     _fmt(m["frac_over_5pct"], pct=True)])
    if fd.seen_vs_heldout_lane is not None:
        rows.append(["seen vs other on-lane views (content change only)",
                     _fmt(fd.seen_vs_heldout_lane["value"]), "", "", "", ""])
    fd_table = _table(["comparison", "FD EffNet-Lite0", "nearest train cam (m)", "|yaw| (deg)",
                       "multi-view depth err (median)", "> 5 %"], rows)
    if fd.prior_baseline is not None:
        pb = fd.prior_baseline
        pb_rows = [[f"{b} m", _fmt(pb["scene_novel_over_content"][b], digits=3),
                    _fmt(pb["prior_novel_over_content"][b], digits=3),
                    _fmt(pb["scene_over_prior"][b], digits=3)] for b in bins]
        fd_table += ("<h3>Novel views against the prior's own images of the same views</h3>"
                     "<p>FD seen vs novel over FD seen vs other on-lane views (content change), "
                     "for the scene and for the prior's images at t = 1 of the same cameras: "
                     "a scene that reproduced its prior exactly would score the prior's ratio."
                     "</p>" + _table(["novel bin", "scene", f"prior ({html.escape(pb['prior'])})",
                                       "scene / prior"], pb_rows))
    ref = ""
    if fd.vs_reference is not None:
        r = fd.vs_reference
        ref_rows = [["seen vs reference", _fmt(r["seen"]["value"])],
                    ["novel vs reference", _fmt(r["novel"]["value"])]]
        ref_rows += [[f"novel {b} m vs reference", _fmt(r["novel_per_bin"][b]["value"])] for b in bins]
        ref = "<h2>Against the reference images</h2>" + _table(["comparison", "FD EffNet-Lite0"], ref_rows)
    geo_rows = []
    for split in ("seen", "novel"):
        g = getattr(result.geometry, split)
        for name, s in list(g["per_class"].items()) + [("all classes", g["all"])]:
            geo_rows.append([split, html.escape(name), s["pixels"], _fmt(s["coverage"], pct=True),
                             _fmt(s["depth_rel_err_median"], pct=True),
                             _fmt(s["normal_err_deg_median"], digits=2),
                             _fmt(s["normal_err_deg_p90"], digits=2)])
    geo = _table(["views", "class", "proxy pixels", "surfel coverage", "depth err (median)",
                  "normal err deg (median)", "normal err deg (p90)"], geo_rows)
    t = result.temporal
    temp = _table(["path", "frames", "warp err (mean |ΔsRGB|)", "naive frame diff", "valid pixels"],
                  [[f"lane {html.escape(str(t.get('lane')))}, {t.get('path_m')} m", t["pairs"] + 1,
                    _fmt(t["warp_err"], digits=4), _fmt(t["naive_err"], digits=4),
                    _fmt(t["valid_frac"], pct=True)]])
    def img(key, alt):
        return f'<p><img src="{images[key]}" alt="{alt}"></p>' if key in images else ""

    dfd = ""
    if result.deferred is not None:
        dr = result.deferred
        d = dr.provenance
        td = dr.temporal
        d_rows = [["seen vs all novel", _fmt(fd.seen_vs_novel.overall["value"]),
                   _fmt(dr.seen_vs_novel.overall["value"])]]
        d_rows += [[f"seen vs novel {b} m", _fmt(fd.seen_vs_novel.per_bin[b]["value"]),
                    _fmt(dr.seen_vs_novel.per_bin[b]["value"])] for b in bins]
        d_rows.append(["seen + novel vs the prior's own images (t = 1)",
                       _fmt(dr.vs_prior_raw["value"]), _fmt(dr.vs_prior_deferred["value"])])
        d_rows.append(["temporal warp err", _fmt(t["warp_err"], digits=4),
                       _fmt(td["warp_err"], digits=4)])
        d_rows.append(["naive frame diff", _fmt(t["naive_err"], digits=4),
                       _fmt(td["naive_err"], digits=4)])
        dfd = (f"<h2>Deferred rendering</h2><p>Prior {html.escape(str(d['prior']))} "
               f"({html.escape(str(d['prior_source']))}), strength T = {d['strength']}, "
               f"N = {d['steps']} steps, seed {d['seed']}, "
               f"{_fmt(d.get('s_per_frame'), digits=3)} s per frame.</p>"
               + _table(["measure", "raw", "deferred"], d_rows)
               + img("deferred", "raw and deferred frames side by side"))
    unav = "".join(f"<li><b>{html.escape(u['metric'])}</b>: unavailable: {html.escape(u['reason'])}</li>"
                   for u in result.unavailable)
    warn = "".join(f"<li>{html.escape(w)}</li>" for w in result.warnings)

    c = result.counts
    return f"""<!doctype html>
<html><head><meta charset="utf-8"><title>lsd3d-usd eval: {html.escape(Path(result.scene).name)}</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:1em auto;color:#222}}
table{{border-collapse:collapse;margin:.5em 0}}td,th{{border:1px solid #bbb;padding:2px 8px;
text-align:right}}th{{background:#eee}}td:first-child,td:nth-child(2){{text-align:left}}
img{{max-width:100%}}code{{background:#f4f4f4}}</style></head><body>
<h1>Evaluation of <code>{html.escape(result.scene)}</code></h1>
<p>Seen views: {html.escape(result.seen_views_source)}. {c.seen} seen and {c.novel} novel views
({c.novel_per_bin} per distance bin), {c.trajectory_frames} trajectory frames at
{result.resolution[0]}×{result.resolution[1]}, {result.surfels:,} surfels, layers
{html.escape(', '.join(result.composed_layers))}; tone map {html.escape(result.tonemap)};
seed {result.seed}.</p>
<h2>Seen and novel views</h2>{img('contact_sheet', 'contact sheet')}
<h2>Elevated views (novel_elevated)</h2>{_elevated_html(result)}{img('elevated', 'elevated views')}
<h2>Off the training path (novel_off_path)</h2>{_off_path_html(result)}{img('off_path', 'off-path views per bin: prior and surfels')}
<h2>PSNR per class</h2>{_class_html(result)}
<h2>Fréchet distance of EfficientNet-Lite0 features (fd_effnet_lite0; not FID)</h2>
{fd_table}{img('fd_plot', 'FD by distance')}{ref}
<h2>Geometry against the proxy</h2>{geo}{img('geometry', 'geometry panel')}
<h2>Temporal consistency</h2>{temp}{img('temporal', 'temporal path')}
{dfd}
<h2>Chunk seams</h2>{_seams_html(result)}
<h2>GGDS loss</h2>{img('loss', 'GGDS loss curve') or '<p>no loss curve (no GGDS run)</p>'}
<h2>Not computed</h2><ul>{unav}</ul>
{'<h2>Warnings</h2><ul>' + warn + '</ul>' if warn else ''}
<p>Timings (s): {html.escape(json.dumps(result.timings))}</p>
</body></html>
"""


def write_report(out_dir: Path, result: EvalResult, sc, seen_img, novel_img, novel, traj_img, *,
                 seen_frames, seen_gb, deferred=None, elevated=None, off_path=None) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    files = {"contact_sheet": contact_sheet(out_dir / "eval_contact_sheet.png", seen_img, novel_img,
                                            novel, result.bins_m),
             "fd_plot": fd_plot(out_dir / "eval_fd.png", result),
             "geometry": geometry_panel(out_dir / "eval_geometry.png", seen_img[0], seen_frames[0],
                                        seen_gb[0]),
             "temporal": temporal_panel(out_dir / "eval_temporal.png", traj_img,
                                        result.temporal,
                                        result.deferred.temporal
                                        if result.deferred is not None else None)}
    if elevated is not None and elevated[0]:
        files["elevated"] = elevated_sheet(out_dir / "eval_elevated.png", *elevated)
    if off_path is not None and off_path[0].views:
        files["off_path"] = off_path_sheet(out_dir / "eval_off_path.png", *off_path)
    if deferred is not None:
        files["deferred"] = deferred_sheet(out_dir / "eval_deferred.png", seen_img, deferred, traj_img)
    if result.run:
        loss = sc.root / "ggds" / result.run / "loss.png"
        if loss.is_file():
            files["loss"] = S.atomic_write_bytes(out_dir / "loss.png", loss.read_bytes())
    images = {k: Path(v).name for k, v in files.items()}
    files["html"] = S.atomic_write_bytes(out_dir / "report.html", html_report(result, images).encode())
    files["json"] = out_dir / "eval.json"
    return files
