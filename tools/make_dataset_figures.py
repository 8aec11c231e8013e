"""Figures of `lsd3d-usd dataset` output drawn by the nuScenes devkit's own renderers
(docs/datasets.md): CAM_FRONT with the annotations' boxes, LIDAR_TOP coloured by lidarseg,
and the keyframe sweep projected into CAM_FRONT, saved as 1000 px wide JPEGs. Needs
nuscenes-devkit (docs/datasets.md).

    python tools/make_dataset_figures.py --scene SCENE [--out docs/images] [--width 800]
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import lsd3d_usd  # noqa: F401

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, help="a generated scene folder")
    ap.add_argument("--out", default=str(ROOT / "docs" / "images"))
    ap.add_argument("--width", type=int, default=800)
    ap.add_argument("--route", default="w_in,j_we,e_out")
    ap.add_argument("--seconds", type=float, default=4.0)
    args = ap.parse_args()
    import matplotlib
    matplotlib.use("Agg")
    from nuscenes.nuscenes import NuScenes

    from lsd3d_usd.datasets.build import DatasetOptions, build_dataset
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        ds = Path(tmp) / "ds"
        build_dataset([args.scene], ds, DatasetOptions(
            route=args.route, seconds=args.seconds, camera_hz=2, lidar_hz=2, keyframe_hz=2,
            width=args.width), progress=True)
        nusc = NuScenes(version="v1.0-lsd3d", dataroot=str(ds), verbose=False)
        s = nusc.sample[-1]
        png = Path(tmp)
        nusc.render_sample_data(s["data"]["CAM_FRONT"], out_path=str(png / "dataset_cam_front.png"),
                                verbose=False)
        # the map underlay is left out: the devkit's crop_image fails on numpy 2
        nusc.render_sample_data(s["data"]["LIDAR_TOP"], show_lidarseg=True, underlay_map=False,
                                axes_limit=30, out_path=str(png / "dataset_lidarseg.png"),
                                verbose=False)
        nusc.render_pointcloud_in_image(s["token"], out_path=str(png / "dataset_pc_in_image.png"),
                                        verbose=False, dot_size=3)
        from PIL import Image
        for n in ("dataset_cam_front", "dataset_lidarseg", "dataset_pc_in_image"):
            im = Image.open(png / f"{n}.png").convert("RGB")
            w, h = im.size
            im.resize((1000, round(h * 1000 / w)), Image.LANCZOS).save(out / f"{n}.jpg",
                                                                          quality=85)
            print(out / f"{n}.jpg")


if __name__ == "__main__":
    main()
