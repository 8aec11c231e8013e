"""Contact sheet of environment maps over time of day x weather x season (tone-mapped PNG).

    python tools/env_contact_sheet.py [-o docs/images/env_contact_sheet.png] [--tile 192]

Rows: dawn, sunrise, morning, noon, sunset, dusk, night in summer, then spring, autumn and
winter afternoons; columns: the six weathers. Madrid. Exposure adapts only partly to each
map's brightness (key^0.8), so dusk and night stay dark, as they are.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

TIMES = ["dawn", "sunrise", "morning", "noon", "sunset", "dusk", "night"]
WEATHERS = ["clear", "partly-cloudy", "overcast", "fog", "rain", "snow"]
SEASON_ROWS = ["spring", "autumn", "winter"]


def tonemap(img: np.ndarray, ref_key: float = 8.0) -> np.ndarray:
    lum = img @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    sky = lum[: img.shape[0] // 2]
    key = float(np.exp(np.mean(np.log(sky + 1e-9))))
    x = img * (0.18 / (key ** 0.8 * ref_key ** 0.2))
    x = x / (1.0 + x)
    x = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0), 1 / 2.4) - 0.055)
    return np.clip(x, 0, 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--output", default="docs/images/env_contact_sheet.png")
    ap.add_argument("--tile", type=int, default=192, help="tile width (height = width / 2)")
    ap.add_argument("--city", default="madrid")
    args = ap.parse_args()

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from lsd3d_usd.env import render_sky
    from lsd3d_usd.env.prompt import build_params

    W, H = args.tile, args.tile // 2
    rows = [(f"{t}", dict(time_of_day=t, season="summer")) for t in TIMES]
    rows += [(f"{s} afternoon", dict(time_of_day="afternoon", season=s)) for s in SEASON_ROWS]
    grid = np.zeros((len(rows) * H, len(WEATHERS) * W, 3), np.float32)
    for r, (_, kw) in enumerate(rows):
        for c, weather in enumerate(WEATHERS):
            p, _ = build_params(f"in {args.city}", weather=weather, **kw)
            grid[r * H:(r + 1) * H, c * W:(c + 1) * W] = tonemap(render_sky(p, W, H))
        print(f"row {r + 1}/{len(rows)}: {rows[r][0]}")

    dpi = 100
    fig = plt.figure(figsize=(grid.shape[1] / dpi + 1.3, grid.shape[0] / dpi + 0.4), dpi=dpi)
    ax = fig.add_axes([1.3 / (grid.shape[1] / dpi + 1.3), 0, grid.shape[1] / dpi /
                       (grid.shape[1] / dpi + 1.3), grid.shape[0] / (grid.shape[0] + 40)])
    ax.imshow(grid, interpolation="nearest")
    ax.set_xticks([W * (c + 0.5) for c in range(len(WEATHERS))], WEATHERS, fontsize=9)
    ax.xaxis.tick_top()
    ax.set_yticks([H * (r + 0.5) for r in range(len(rows))], [name for name, _ in rows], fontsize=9)
    ax.tick_params(length=0)
    for s in ax.spines.values():
        s.set_visible(False)
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
