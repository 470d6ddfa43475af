"""Write a test crowd: a USD stage referencing characters many times, each with its own time offset
and transform, every other one instanceable.

    python tools/make_crowd.py out/crowd.usda [--count 1000] [--asset PATH ...] [--seed 0]

By default the characters are the bundled humanoid (``dqskin/assets/humanoid.usda``) and
CesiumMan from ``../shared/assets`` (when present), referenced by absolute path -- nothing is
copied, so the stage stays small. Instance ``k`` gets asset ``k mod n``, a layer offset (its
clip starts ``offset`` time codes later, a USD ``LayerOffset``), a place on a grid and a turn about
+Y. ``dqskin skin out/crowd.usda --out cache.usdc`` skins it with one FK launch and one skinning
launch per method per block of frames.
"""

import argparse
import sys
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_ASSETS = (ROOT / "assets" / "humanoid.usda",
                  ROOT.parent / "shared" / "assets" / "usd-wg" / "CesiumMan" / "CesiumMan.usdz")


def write_crowd(out, assets, count, *, seed=0, spacing=150.0, instanceable_every=2,
                max_offset=24.0):
    """Write the crowd stage to ``out``; returns the instance prim paths.

    Parameters
    ----------
    out : path
        A new ``.usda``/``.usdc`` layer (overwritten).
    assets : list of paths
        Characters (each a stage with a default prim holding a SkelRoot).
    count : int
        Instances; instance ``k`` references ``assets[k % len(assets)]``.
    seed : int
        Offsets and turns are drawn from it (reproducible).
    spacing : float
        Grid spacing, in the stage's units.
    instanceable_every : int
        Every n-th instance is instanceable (0: none).
    max_offset : float
        Layer offsets are drawn from ``[0, max_offset)`` time codes.
    """
    rng = np.random.default_rng(seed)
    assets = [Path(a).resolve() for a in assets]
    first = Usd.Stage.Open(str(assets[0]))
    stage = Usd.Stage.CreateNew(str(out))
    stage.SetTimeCodesPerSecond(first.GetTimeCodesPerSecond())
    stage.SetStartTimeCode(first.GetStartTimeCode())
    stage.SetEndTimeCode(first.GetEndTimeCode())
    UsdGeom.SetStageUpAxis(stage, UsdGeom.GetStageUpAxis(first))
    UsdGeom.SetStageMetersPerUnit(stage, UsdGeom.GetStageMetersPerUnit(first))
    root = UsdGeom.Xform.Define(stage, "/Crowd")
    stage.SetDefaultPrim(root.GetPrim())
    side = max(1, int(np.ceil(np.sqrt(count))))
    paths = []
    for k in range(count):
        # typeless def: the referenced prim's type (SkelRoot, Xform) comes through
        x = UsdGeom.Xformable(stage.DefinePrim(f"/Crowd/c{k:04d}"))
        offset = float(np.round(rng.uniform(0.0, max_offset), 3))
        x.GetPrim().GetReferences().AddReference(
            Sdf.Reference(str(assets[k % len(assets)]), layerOffset=Sdf.LayerOffset(offset)))
        x.AddTranslateOp().Set(Gf.Vec3d(spacing * (k % side), 0.0, spacing * (k // side)))
        x.AddRotateYOp().Set(float(rng.uniform(0.0, 360.0)))
        if instanceable_every and k % instanceable_every == 0:
            x.GetPrim().SetInstanceable(True)
        paths.append(str(x.GetPath()))
    stage.GetRootLayer().Save()
    return paths


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="the crowd stage to write (.usda/.usdc)")
    ap.add_argument("--count", type=int, default=1000)
    ap.add_argument("--asset", action="append", help="a character stage (repeatable); default: "
                    "the bundled humanoid and ../shared's CesiumMan")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    assets = args.asset or [a for a in DEFAULT_ASSETS if a.exists()]
    missing = [a for a in assets if not Path(a).exists()]
    if missing:
        print(f"make_crowd: no such asset: {missing[0]}", file=sys.stderr)
        return 2
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    paths = write_crowd(args.out, assets, args.count, seed=args.seed)
    print(f"wrote {args.out}: {len(paths)} instances of {len(assets)} characters "
          f"({', '.join(Path(a).name for a in assets)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
