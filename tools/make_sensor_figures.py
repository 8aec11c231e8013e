"""Figures of the sensor outputs (docs/sensors.md): one nuscenes6 frame of a scene (default:
the README sample generated with generate's defaults, given with --scene) as RGB / depth /
semantic / instance side by side, the hdl32 and waymo_top sweeps from the same pose in a
bird's-eye view, and the LiDAR points projected into CAM_FRONT.

    python tools/make_sensor_figures.py --scene SCENE [--out docs/images] [--time 2.0]
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

import lsd3d_usd  # noqa: F401

ROOT = Path(__file__).resolve().parents[1]


def _colour_depth(z: np.ndarray) -> np.ndarray:
    """Inverse depth through matplotlib's turbo map (near warm, far cold), sky black."""
    from matplotlib import colormaps
    inv = np.where(np.isfinite(z), 1.0 / np.maximum(z, 1e-3), 0.0)
    hi = np.percentile(inv[inv > 0], 99) if (inv > 0).any() else 1.0
    rgb = colormaps["turbo"](np.clip(inv / hi, 0, 1))[..., :3]
    rgb[~np.isfinite(z)] = 0.0
    return (rgb * 255).astype(np.uint8)


def _colour_instances(ins: np.ndarray) -> np.ndarray:
    rng = np.random.default_rng(3)
    pal = rng.integers(60, 255, (int(ins.max()) + 1, 3)).astype(np.uint8)
    pal[0] = (30, 30, 30)
    return pal[ins]


def _label(img: np.ndarray, text: str) -> np.ndarray:
    from PIL import Image, ImageDraw
    im = Image.fromarray(img)
    d = ImageDraw.Draw(im)
    d.rectangle([0, 0, 8 * len(text) + 10, 20], fill=(0, 0, 0))
    d.text((5, 4), text, fill=(255, 255, 255))
    return np.asarray(im)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", required=True, help="a generated scene folder")
    ap.add_argument("--out", default=str(ROOT / "docs" / "images"))
    ap.add_argument("--time", type=float, default=2.0, help="seconds into the default route")
    ap.add_argument("--width", type=int, default=640)
    args = ap.parse_args()
    from lsd3d_usd.render.camera import from_usd
    from lsd3d_usd.views import rig
    from lsd3d_usd.views.images import read_image, write_image
    from lsd3d_usd.views.options import RigOptions
    from lsd3d_usd.sensors.rigs import load_rig
    from pxr import Usd
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # the clip up to --time, so the frame of interest is its last; one per LiDAR
        fps = 1.0 / args.time if args.time > 0 else 1.0
        renders = {}
        for lidar in ("hdl32", "waymo_top"):
            renders[lidar] = rig.render_rig(
                args.scene, tmp / lidar,
                RigOptions(name="nuscenes6", seconds=args.time + 1e-6, fps=fps, lidar=lidar,
                           video=False, overview=False),
                width=args.width, outputs=("rgb", "depth", "semantic", "instance"),
                progress=False, log=lambda *_: None)
        res = renders["hdl32"]
        k = len(res.frames["CAM_FRONT"]) - 1
        stem = str(res.frames["CAM_FRONT"][k])[:-4]
        rgb = (read_image(stem + ".png")[..., :3] * 255).astype(np.uint8)
        z = read_image(stem + ".depth.exr")[..., 0]
        sem = (read_image(stem + ".semantic_preview.png")[..., :3] * 255).astype(np.uint8)
        ins = np.round(read_image(stem + ".instance.png")[..., 0] * 65535).astype(np.int64)
        panels = [_label(rgb, "RGB"), _label(_colour_depth(z), "depth (1/z)"),
                  _label(sem, "semantic"), _label(_colour_instances(ins), "instance")]
        top = np.concatenate(panels[:2], 1)
        bottom = np.concatenate(panels[2:], 1)
        write_image(out / "sensors_gt.png", np.concatenate([top, bottom], 0))
        # bird's-eye views of the two LiDARs' sweeps at that frame
        bevs = [_label((read_image(tmp / name / "LIDAR_TOP" / f"{k:04d}_bev.png")[..., :3] * 255)
                       .astype(np.uint8), f"{name} (100 m across, coloured by class)")
                for name in ("hdl32", "waymo_top")]
        write_image(out / "sensors_lidar_bev.png", np.concatenate(bevs, 1))
        # waymo_top points projected into CAM_FRONT, coloured by range
        sw = np.load(renders["waymo_top"].sweeps[k])
        stage = Usd.Stage.Open(str(renders["waymo_top"].rig_layer))
        tcps = stage.GetTimeCodesPerSecond()
        t = k / fps
        spec = load_rig("nuscenes6").camera("CAM_FRONT")
        prim = next(p for p in stage.Traverse() if p.GetName() == "CAM_FRONT")
        cam = from_usd(prim, round(t * tcps, 6), args.width, spec.height_for(args.width))
        pc = sw["xyz_world"] @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
        front = pc[:, 2] > 0.5
        uv = (pc[front] @ cam.K.T)[:, :2] / pc[front, 2:3]
        r = sw["range"][front]
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        from matplotlib import colormaps
        col = (colormaps["turbo"](np.clip(r[inside] / 40.0, 0, 1))[:, :3] * 255).astype(np.uint8)
        img = (rgb * 0.45).astype(np.uint8)
        order = np.argsort(-r[inside])              # near points drawn last
        u = uv[inside][order].astype(int)
        for du in (0, 1):
            for dv in (0, 1):
                img[np.clip(u[:, 1] + dv, 0, cam.height - 1), np.clip(u[:, 0] + du, 0, cam.width - 1)] = col[order]
        write_image(out / "sensors_lidar_in_camera.png",
                    _label(img, "waymo_top points in CAM_FRONT (colour: range, 0-40 m)"))
    print(f"wrote {out}/sensors_gt.png, sensors_lidar_bev.png, sensors_lidar_in_camera.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
