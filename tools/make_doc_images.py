"""Render the documentation's images with dqskin's own offscreen renderer.

Writes ``docs/images/``:

* ``twist_methods.png``: the bundled twist cylinder at frame 24 (180° of twist about the bone),
  skinned with LBS, DQS, blend and CoR side by side (LBS's candy wrapper).
* ``bend_methods.png``: the bundled bending arm at frame 30 (150° elbow bend), the same four
  methods (LBS's volume loss at the elbow, DQS's bulge).
* ``report_panel.png``: one panel of ``dqskin compare`` on the bundled humanoid (the worst frame,
  front view), as the report shows it.

Run ``python tools/make_doc_images.py [--out docs/images]``; the images are committed, so run it
again only when the renderer or the assets change.
"""

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

import dqskin
from dqskin.report.render import Camera, MeshRenderer, save_png, side_by_side

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("lbs", "dqs", "blend", "cor")
LABELS = {"lbs": "LBS", "dqs": "DQS", "blend": "blend", "cor": "CoR"}


def methods_image(asset, frame, view, width):
    """(H, W, 3) uint8: every method of :data:`METHODS` at ``frame``, one camera for all."""
    scene = dqskin.load(str(ROOT / "assets" / asset))
    mesh = scene.meshes[0]
    posed = {m: scene.skin([float(frame)], m).points[mesh.name][0] for m in METHODS}
    everything = np.concatenate([mesh.points, *posed.values()])
    camera = Camera.frame(everything.min(axis=0), everything.max(axis=0), view, aspect=1.5)
    renderer = MeshRenderer(posed["lbs"], mesh.faces, device="cpu")
    images = []
    for m in METHODS:
        renderer.update(posed[m])
        images.append(renderer.render(camera, width=width, height=width * 2 // 3,
                                      supersample=2))
    return side_by_side(images, [LABELS[m] for m in METHODS])


def report_panel(out, width):
    """Copy one front-view panel of ``dqskin compare`` on the bundled humanoid to ``out``."""
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "dqskin.cli", "compare",
                        str(ROOT / "assets" / "humanoid.usda"), "--out", f"{tmp}/report",
                        "--frames", "12", "--views", "front", "--width", str(width),
                        "--viewer-frames", "0", "--no-sweeps", "--quiet"], check=True)
        panels = sorted(Path(tmp, "report", "frames").glob("*front*.png"))
        if not panels:
            raise SystemExit(f"no front panel in {tmp}/report/frames")
        shutil.copyfile(panels[0], out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "images"))
    ap.add_argument("--width", type=int, default=240, help="pixels per method panel")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    save_png(out / "twist_methods.png",
             methods_image("twist_cylinder.usda", 24, "three_quarter", args.width))
    save_png(out / "bend_methods.png",
             methods_image("bending_arm.usda", 30, "front", args.width))
    report_panel(out / "report_panel.png", 320)
    for p in sorted(out.glob("*.png")):
        print(p.relative_to(ROOT) if p.is_relative_to(ROOT) else p)


if __name__ == "__main__":
    main()
