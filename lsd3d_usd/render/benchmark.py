"""Render benchmark: run time against error of the CPU 2DGS rasteriser (`lsd3d-usd bench render`).

Synthetic, seeded driving scene: surfels over a ground plane and on the faces of boxes
(buildings / parked cars) along a road, seen by a camera at driving height. For each
configuration it measures forward and backward wall time, splat-pixel evaluations per second
(evaluations counted by the kernel; rate over the forward kernel time), peak RSS during the
configuration, and the error against the float64 reference. The reference is evaluated on
fixed 32x32 pixel crops (two, at the road and at the horizon) with all surfels whose exact,
conservative screen bound touches the crop (bounds are tested conservative separately), so it
stays tractable for millions of surfels. The machine's float32 peak is measured with a large
matmul; peak_fraction = evals/s * 50 flops / peak.
"""
from __future__ import annotations

import json
import math
import os
import threading
import time

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import torch

from lsd3d_usd.render import kernels_prep as kprep
from lsd3d_usd.render import projection as proj
from lsd3d_usd.render.raster_types import RasterSettings
from lsd3d_usd.render.rasterize import rasterize
from lsd3d_usd.render.reference import render_reference

FLOPS_PER_EVAL = 50


# ---------------------------------------------------------------- scene ---
def driving_scene(n: int, seed: int = 0, sh_degree: int = 1):
    """n surfels (numpy float32 arrays): 70% on the ground plane z=0 over x in [-30, 30],
    y in [0, 150]; 30% on the faces of boxes along both roadsides. Scales from the area per
    surfel, random opacity and SH."""
    rng = np.random.default_rng(seed)
    n_ground = int(n * 0.7)
    n_box = n - n_ground
    ground_area = 60.0 * 150.0
    pos_g = np.stack([rng.uniform(-30, 30, n_ground), rng.uniform(0, 150, n_ground),
                      np.zeros(n_ground)], 1)
    q_g = np.tile([0.0, 0.0, 0.0, 1.0], (n_ground, 1))
    s_g = np.full((n_ground, 2), 0.8 * math.sqrt(ground_area / max(n_ground, 1)))
    # boxes: 30 per side, 6-14 m wide, 4-20 m high; surfels on the road-facing and top faces
    nb = 60
    side = np.where(np.arange(nb) < nb // 2, -1.0, 1.0)
    bx0 = side * rng.uniform(8, 12, nb)
    by0 = rng.uniform(0, 150, nb)
    bw = rng.uniform(6, 14, nb)
    bh = rng.uniform(4, 20, nb)
    face_area = bw * bh
    box = rng.choice(nb, n_box, p=face_area / face_area.sum())
    u = rng.uniform(-0.5, 0.5, n_box)
    v = rng.uniform(0, 1, n_box)
    pos_b = np.stack([bx0[box], by0[box] + u * bw[box], v * bh[box]], 1)
    # facade normal along -+x (towards the road): rotate z onto x about y
    c = math.sqrt(0.5)
    q_b = np.where(side[box][:, None] < 0, [[0.0, c, 0.0, c]], [[0.0, -c, 0.0, c]])
    s_b = np.full((n_box, 2), 0.8 * math.sqrt(face_area.sum() / max(n_box, 1)))
    pos = np.concatenate([pos_g, pos_b]).astype(np.float32)
    quats = np.concatenate([q_g, q_b]).astype(np.float32)
    quats += rng.normal(0, 0.05, quats.shape).astype(np.float32)  # not perfectly axis aligned
    scales = np.concatenate([s_g, s_b]).astype(np.float32)
    scales *= rng.uniform(0.6, 1.4, scales.shape).astype(np.float32)
    opac = rng.uniform(0.4, 1.0, n).astype(np.float32)
    k = (sh_degree + 1) ** 2
    sh = (rng.normal(0, 0.15, (n, k, 3)) / np.arange(1, k + 1)[None, :, None]).astype(np.float32)
    sh[:, 0, :] += rng.uniform(-1.0, 1.0, (n, 3)).astype(np.float32)
    return pos, quats, scales, opac, sh


def driving_camera(width: int, height: int, hfov_deg: float = 90.0):
    """OpenCV viewmat at (0, -5, 1.6) looking along +y, and K."""
    eye = np.array([0.0, -5.0, 1.6])
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # rows: x, y(down), z(fwd)
    vm = np.eye(4, dtype=np.float32)
    vm[:3, :3] = R
    vm[:3, 3] = -R @ eye
    f = width / (2 * math.tan(math.radians(hfov_deg) / 2))
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], np.float32)
    return vm, K


# -------------------------------------------------------------- helpers ---
def float32_peak_flops(seconds: float = 1.0) -> float:
    """Measured float32 matmul FLOP/s (best of several 1024^3 products)."""
    a = torch.randn(1024, 1024)
    b = torch.randn(1024, 1024)
    torch.mm(a, b)
    best = 0.0
    t_end = time.perf_counter() + seconds
    while time.perf_counter() < t_end:
        t0 = time.perf_counter()
        torch.mm(a, b)
        best = max(best, 2 * 1024 ** 3 / (time.perf_counter() - t0))
    return best


class RssPeak:
    """Peak resident memory (MB) while active, sampled from /proc/self/status."""

    def __enter__(self):
        self.peak = _rss_mb()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        return self

    def _run(self):
        while not self._stop.wait(0.005):
            self.peak = max(self.peak, _rss_mb())

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, _rss_mb())


def _rss_mb() -> float:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def _crops(width, height, size=32):
    """Two fixed crops: road just below the image centre, and the horizon at the right side."""
    size = min(size, width, height)
    spots = [(width // 2 - size // 2, int(height * 0.75) - size // 2),
             (int(width * 0.8) - size // 2, height // 2 - size // 2)]
    pix = []
    for x0, y0 in spots:
        x0 = min(max(x0, 0), width - size)
        y0 = min(max(y0, 0), height - size)
        jj, ii = np.meshgrid(np.arange(y0, y0 + size), np.arange(x0, x0 + size), indexing="ij")
        pix.append(np.stack([ii.ravel(), jj.ravel()], 1))
    return np.concatenate(pix)


def reference_on_crops(arrays, vm, K, width, height, *, sh_degree, near=0.05, far=1e4,
                       alpha_min=1.0 / 255.0, alpha_max=0.99):
    """float64 reference (no early stop) on the crop pixels; surfels pre-selected by their exact
    conservative bound touching the crops' bounding rectangles."""

    means, quats, scales, opac, sh = (torch.from_numpy(a) for a in arrays)
    vm_t, K_t = torch.from_numpy(vm), torch.from_numpy(K)
    pix = _crops(width, height)
    with torch.no_grad():
        rot, centre = proj.camera_frame(vm_t)
        _, vis, rect, _, _ = kprep.project(*arrays, 0, rot.numpy(), centre.numpy(),
                                           K.astype(np.float64), width, height, near, far,
                                           alpha_min, -1.0)
        sel = np.zeros(len(vis), bool)
        for c in range(0, len(pix), 1024):
            cp = pix[c:c + 1024]
            x0, x1, y0, y1 = cp[:, 0].min(), cp[:, 0].max(), cp[:, 1].min(), cp[:, 1].max()
            sel |= vis & (rect[:, 0] <= x1) & (rect[:, 1] >= x0) & (rect[:, 2] <= y1) & (rect[:, 3] >= y0)
        idx = torch.arange(len(vis))
        use = idx[torch.from_numpy(sel)]
        ref = render_reference(means[use], quats[use], scales[use], opac[use], sh[use], vm_t, K_t,
                               width, height, near=near, far=far, sh_degree=sh_degree,
                               alpha_min=alpha_min, alpha_max=alpha_max,
                               pixels=torch.from_numpy(pix), chunk=2048)
    return pix, ref, int(use.numel())


# ------------------------------------------------------------ one config ---
def run_config(n, width, height, *, seed=0, sh_degree=1, bound_sigma=None, t_min=1e-4,
               alpha_min=1.0 / 255.0, reference=True, peak_flops=None, label="default",
               repeats=3):
    """One configuration: forward + backward `repeats` times (timings are medians, with the
    minimum and the list kept: shared cores are noisy), peak RSS over all of them, then the
    error against the float64 reference."""

    arrays = driving_scene(n, seed=seed, sh_degree=max(sh_degree, 1) if sh_degree else 0)
    vm, K = driving_camera(width, height)
    names = ("means", "quats", "scales", "opacities", "sh")
    settings = RasterSettings(sh_degree=sh_degree, bound_sigma=bound_sigma, t_min=t_min,
                              alpha_min=alpha_min)
    runs = []
    with RssPeak() as mem:
        for _ in range(max(1, int(repeats))):
            params = {k: torch.from_numpy(a).requires_grad_(True) for k, a in zip(names, arrays)}
            t0 = time.perf_counter()
            out = rasterize(**params, viewmat=torch.from_numpy(vm), K=torch.from_numpy(K),
                            width=width, height=height, settings=settings)
            fwd_s = time.perf_counter() - t0
            g = torch.Generator().manual_seed(1)
            loss = ((out.rgb * torch.rand(out.rgb.shape, generator=g)).sum()
                    + out.alpha.sum() + 0.01 * out.depth_expected.sum() + out.normal.sum())
            t0 = time.perf_counter()
            loss.backward()
            bwd_s = time.perf_counter() - t0
            st = out.stats
            runs.append(dict(fwd_s=fwd_s, bwd_s=bwd_s, kernel_s=st.timings["raster_s"],
                             project_s=st.timings["project_s"], bin_s=st.timings["bin_s"],
                             bwd_kernel_s=st.timings["backward_kernel_s"],
                             bwd_numba_s=st.timings["backward_s"]))
            del params, loss
    med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
    evals = st.evals
    rec = dict(label=label, n=n, width=width, height=height, sh_degree=sh_degree,
               bound_sigma=bound_sigma, t_min=t_min, alpha_min=alpha_min,
               fwd_s=med["fwd_s"], bwd_s=med["bwd_s"], repeats=len(runs),
               fwd_s_min=min(r["fwd_s"] for r in runs), bwd_s_min=min(r["bwd_s"] for r in runs),
               fwd_s_all=[r["fwd_s"] for r in runs], bwd_s_all=[r["bwd_s"] for r in runs],
               evals=evals, evals_per_s=evals / med["kernel_s"], evals_per_s_total=evals / med["fwd_s"],
               evals_rect=st.evals_rect, rect_evals_per_s=st.evals_rect / med["kernel_s"],
               fwd_kernel_s=med["kernel_s"], fwd_project_s=med["project_s"], fwd_bin_s=med["bin_s"],
               bwd_kernel_s=med["bwd_kernel_s"], bwd_numba_s=med["bwd_numba_s"],
               n_visible=st.n_visible, n_pairs=st.n_pairs, peak_rss_mb=mem.peak,
               load_average=os.getloadavg()[0])
    if peak_flops:
        rec["peak_fraction"] = rec["evals_per_s"] * FLOPS_PER_EVAL / peak_flops
    if reference:
        t0 = time.perf_counter()
        # always against the default-threshold reference: the error of the setting itself
        pix, ref, n_ref = reference_on_crops(arrays, vm, K, width, height, sh_degree=sh_degree)
        jj, ii = torch.from_numpy(pix[:, 1]), torch.from_numpy(pix[:, 0])
        rgb = out.rgb.detach()[jj, ii].double()
        dep = out.depth_expected.detach()[jj, ii].double()
        e_rgb = (rgb - ref["rgb"]).abs()
        e_dep = (dep - ref["depth_expected"]).abs()
        rec.update(max_abs_err=e_rgb.max().item(), mean_abs_err=e_rgb.mean().item(),
                   depth_max_abs_err=e_dep.max().item(), depth_mean_abs_err=e_dep.mean().item(),
                   ref_pixels=len(pix), ref_surfels=n_ref, ref_s=time.perf_counter() - t0)
    else:
        rec.update(max_abs_err=None, mean_abs_err=None)
    return rec


def configs(quick: bool):
    """(label, kwargs) list. Default settings: exact bounds, T 1e-4, alpha 1/255, SH degree 1."""
    if quick:
        return [("n", dict(n=10_000, width=480, height=270)),
                ("n", dict(n=100_000, width=480, height=270)),
                ("n", dict(n=100_000, width=960, height=540)),
                ("bound", dict(n=100_000, width=480, height=270, bound_sigma=3.0)),
                ("t_min", dict(n=100_000, width=480, height=270, t_min=1e-2)),
                ("sh", dict(n=100_000, width=480, height=270, sh_degree=3))]
    out = [("n", dict(n=n, width=960, height=540)) for n in (10_000, 100_000, 1_000_000, 4_000_000)]
    out += [("res", dict(n=1_000_000, width=w, height=h)) for w, h in ((480, 270), (1920, 1080))]
    base = dict(n=1_000_000, width=960, height=540)
    out += [("bound", dict(base, bound_sigma=b)) for b in (3.0, 2.0)]
    out += [("t_min", dict(base, t_min=t)) for t in (1e-3, 1e-2)]
    out += [("alpha_min", dict(base, alpha_min=a)) for a in (1 / 100, 1 / 50)]
    out += [("sh", dict(base, sh_degree=d)) for d in (0, 3)]
    return out


def plot(records, path):
    matplotlib.use("Agg")

    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    for r in records:
        if r.get("max_abs_err") is None:
            continue
        tag = f"{r['label']}: n={r['n'] // 1000}k {r['width']}x{r['height']}"
        extra = {"bound": f" k={r['bound_sigma']}", "t_min": f" T={r['t_min']:g}",
                 "alpha_min": f" a={r['alpha_min']:.3g}", "sh": f" deg={r['sh_degree']}"}.get(r["label"], "")
        for a, key in zip(ax, ("fwd_s", "bwd_s")):
            a.scatter(r[key], max(r["max_abs_err"], 1e-8), s=25)
            a.annotate(tag + extra, (r[key], max(r["max_abs_err"], 1e-8)), fontsize=6)
    for a, name in zip(ax, ("forward", "backward")):
        a.set_xscale("log")
        a.set_yscale("log")
        a.axhline(1e-3, color="r", lw=0.8, ls="--")
        a.set_xlabel(f"{name} time [s]")
        a.set_ylabel("max abs RGB error vs float64 reference")
        a.grid(True, which="both", lw=0.3)
    fig.suptitle("lsd3d-usd CPU 2DGS rasteriser: time vs error")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(json_path=None, quick=False, png_path=None, seed=0, log=print):
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    log(f"cores: {os.cpu_count()}, numba threads: {__import__('numba').get_num_threads()}, "
        f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', 'unset')}, "
        f"load average {os.getloadavg()[0]:.2f}")
    # compile / load the numba kernels outside the timings
    a = driving_scene(2000, seed=seed)
    vm, K = driving_camera(64, 48)
    tmp = {k: torch.from_numpy(x).requires_grad_(True)
           for k, x in zip(("means", "quats", "scales", "opacities", "sh"), a)}
    rasterize(**tmp, viewmat=torch.from_numpy(vm), K=torch.from_numpy(K), width=64,
              height=48).rgb.sum().backward()
    peak = float32_peak_flops()
    log(f"float32 matmul peak: {peak / 1e9:.1f} GFLOP/s -> ceiling {peak / FLOPS_PER_EVAL / 1e6:.0f} M evals/s "
        f"at {FLOPS_PER_EVAL} flops/eval")
    records = []
    hdr = (f"{'config':<28}{'fwd s':>8}{'bwd s':>8}{'Mev/s':>8}{'rectM/s':>8}{'peak%':>7}{'rss MB':>8}"
           f"{'rgb max':>10}{'rgb mean':>10}{'dep max':>10}{'load':>6}")
    log(hdr)
    for label, kw in configs(quick):
        rec = run_config(seed=seed, peak_flops=peak, label=label, **kw)
        records.append(rec)
        name = f"{label} n={rec['n']} {rec['width']}x{rec['height']}"
        if label == "bound":
            name += f" k={rec['bound_sigma']}"
        elif label == "t_min":
            name += f" T={rec['t_min']:g}"
        elif label == "alpha_min":
            name += f" a={rec['alpha_min']:.3g}"
        elif label == "sh":
            name += f" deg={rec['sh_degree']}"
        log(f"{name:<28}{rec['fwd_s']:8.3f}{rec['bwd_s']:8.3f}{rec['evals_per_s'] / 1e6:8.0f}"
            f"{rec['rect_evals_per_s'] / 1e6:8.0f}"
            f"{100 * rec['peak_fraction']:6.1f}%{rec['peak_rss_mb']:8.0f}"
            f"{rec['max_abs_err']:10.2e}{rec['mean_abs_err']:10.2e}{rec['depth_max_abs_err']:10.2e}"
            f"{rec['load_average']:6.1f}")
    result = dict(machine=dict(cores=os.cpu_count(), float32_peak_flops=peak,
                               flops_per_eval=FLOPS_PER_EVAL,
                               omp_wait_policy=os.environ.get("OMP_WAIT_POLICY"),
                               load_average=os.getloadavg()),
                  notes=("fwd_s/bwd_s: medians of `repeats` runs (fwd_s_all/bwd_s_all: each run). "
                         "evals_per_s = kernel-counted splat-pixel evaluations (each surfel on "
                         "the rows of its screen rectangle x the 8-pixel blocks they touch) / "
                         "forward kernel time; rect_evals_per_s counts only pixels inside the "
                         "exact rectangles (the useful part); evals_per_s_total uses the whole "
                         "forward (projection, binning). "
                         "Errors vs the float64 reference (no early stop) on two 32x32 crops. "
                         "Measured on shared cores: timings are noisy."),
                  configs=records)
    if json_path:
        tmp_path = str(json_path) + ".tmp"
        with open(tmp_path, "w") as f:
            json.dump(result, f, indent=1)
        os.replace(tmp_path, json_path)
        log(f"wrote {json_path}")
    if png_path:
        plot(records, png_path)
        log(f"wrote {png_path}")
    return result
