"""Every file a USD stage would open, checked before USD opens any of them.

USD opens a stage's sublayers, references, payloads and value-clip layers itself (clip layers
already in ``Usd.Stage.Open``); a FIFO or a device among them would block it forever.
:func:`open_stage` walks the layer graph with Sdf first, layer by layer, and refuses any such
file (:func:`dqskin.files.inputs.regular_file`); the layers it opened stay open while the stage
opens, so USD reads each once.
"""

import glob
import os
import re

from pxr import Sdf, Tf, Usd

from ..files.inputs import regular_file

__all__ = ["checked_layers", "open_stage"]

_TEMPLATE = re.compile(r"#+(\.#+)?")  # value clips' templateAssetPath: frame digits


def _clip_assets(layer: Sdf.Layer) -> list[str]:
    """Asset paths of the value clips authored in ``layer`` (``clips`` metadata: assetPaths,
    manifests, templates as glob patterns)."""
    found: list[str] = []

    def visit(path: Sdf.Path) -> None:
        if not path.IsPrimPath():
            return
        spec = layer.GetPrimAtPath(path)
        if spec is None or not spec.HasInfo("clips"):
            return
        clips = spec.GetInfo("clips")
        for clip_set in clips.values() if isinstance(clips, dict) else ():
            if not isinstance(clip_set, dict):
                continue
            for asset in clip_set.get("assetPaths", ()) or ():
                found.append(getattr(asset, "path", str(asset)))
            for key in ("manifestAssetPath", "templateAssetPath"):
                asset = clip_set.get(key)
                if asset is not None:
                    text = getattr(asset, "path", str(asset))
                    found.append(_TEMPLATE.sub("*", text) if key == "templateAssetPath" else text)

    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    return found


def checked_layers(path: str | os.PathLike, what: str = "layer") -> list[Sdf.Layer]:
    """The layers the stage rooted at ``path`` reads, opened with Sdf after each file is checked
    to be a regular file (InputError, a ValueError, naming it and the layer that names it).
    Files inside a package (``.usdz``) and paths that resolve to no file are left to USD."""
    root = str(regular_file(path))
    layers: list[Sdf.Layer] = []
    seen = {os.path.realpath(root)}
    todo = [root]
    while todo:
        current = todo.pop()
        try:
            layer = Sdf.Layer.FindOrOpen(current)
        except Tf.ErrorException:
            layer = None
        if layer is None:  # (USD says why when it opens the stage)
            continue
        layers.append(layer)
        if "[" in layer.identifier:  # a layer inside a package: its files are the package's
            continue
        for asset in [*layer.GetCompositionAssetDependencies(), *_clip_assets(layer)]:
            if not asset or "[" in asset:
                continue
            absolute = layer.ComputeAbsolutePath(asset)
            matches = glob.glob(glob.escape(absolute).replace(r"[*]", "*")) if "*" in asset \
                else [absolute]
            for file in matches:
                if not os.path.lexists(file) or os.path.realpath(file) in seen:
                    continue
                seen.add(os.path.realpath(file))
                regular_file(file, f"{what} named by {layer.identifier}")
                if os.path.splitext(file)[1].lower() in (".usd", ".usda", ".usdc", ".usdz"):
                    todo.append(file)
    return layers


def open_stage(path: str | os.PathLike,
               load: Usd.Stage.InitialLoadSet = Usd.Stage.LoadAll) -> Usd.Stage | None:
    """``Usd.Stage.Open(path, load)`` once :func:`checked_layers` has checked every file it
    reads (InputError for one that is not a regular file); None when USD cannot open it,
    Tf.ErrorException as USD raises it."""
    held = checked_layers(path)
    try:
        return Usd.Stage.Open(str(path), load)
    finally:
        del held
