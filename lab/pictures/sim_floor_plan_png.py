"""Render a simulated building's walls (OUT/building.json of `graphslam simulate`) as a floor plan PNG.

The image spans x in [0, width_m], y in [0, height_m] of the site frame (top edge at
y = height_m), as `graphslam survey --floor-plan PNG --floor-size W H` expects.

    python lab/pictures/sim_floor_plan_png.py /tmp/paper/building.json /tmp/paper_plan.png
    # prints: --floor-size 120 60
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from PIL import Image, ImageDraw


def main(building_json: str, out_png: str, px_per_m: float = 10.0) -> None:
    b = json.loads(Path(building_json).read_text(encoding="utf-8"))["building"]
    w_m, h_m = float(b["width_m"]), float(b["height_m"])
    w_px, h_px = round(w_m * px_per_m), round(h_m * px_per_m)
    im = Image.new("RGB", (w_px, h_px), (245, 245, 240))
    draw = ImageDraw.Draw(im)

    def px(x: float, y: float) -> tuple[float, float]:
        return x * w_px / w_m, (h_m - y) * h_px / h_m  # image rows grow downwards

    for x0, y0, x1, y1 in b["walls"]:
        draw.line([px(x0, y0), px(x1, y1)], fill=(60, 60, 70), width=3)
    im.save(out_png)
    print(f"--floor-size {w_m:g} {h_m:g}")


if __name__ == "__main__":
    main(*sys.argv[1:3])
