"""``dqskin compare`` on the Khronos glTF samples: the viewer's rest-pose ghost lies in the space
of the posed frames, checked against the glTF skinning equation evaluated here from the file's
own node matrices (pygltflib and NumPy, float64: ``jointMatrix = global(joint) · IBM`` at the
nodes' rest TRS); the summary shows ties as ties and says why a metric is not measured.
"""

import base64
import json
import re

import numpy as np
import pygltflib
import pytest

from dqskin.report.compare import run_compare, summary_lines
from dqskin.report.viewer import decode

SAMPLES = {"CesiumMan": "CesiumMan.glb", "RiggedFigure": "RiggedFigure.glb",
           "RiggedSimple": "RiggedSimple.glb", "SimpleSkin": "SimpleSkin.gltf"}
_TYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32,
          5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def _buffer(gltf, index, path):
    uri = gltf.buffers[index].uri
    if uri is None:
        return gltf.binary_blob()
    if uri.startswith("data:"):
        return base64.b64decode(uri.split(",", 1)[1])
    return (path.parent / uri).read_bytes()


def _accessor(gltf, index, path):
    """An accessor's values as float64 (count, width), normalized integers dequantized."""
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    dtype = np.dtype(_TYPES[acc.componentType]).newbyteorder("<")
    width = _WIDTH[acc.type]
    stride = view.byteStride or dtype.itemsize * width
    data = _buffer(gltf, view.buffer, path)
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    rows = np.stack([np.frombuffer(data, dtype, width, start + i * stride)
                     for i in range(acc.count)]).astype(np.float64)
    if acc.normalized:
        rows /= np.iinfo(dtype).max
    return rows


def _local(node):
    if node.matrix:
        return np.array(node.matrix, dtype=np.float64).reshape(4, 4).T  # column-major
    t = np.eye(4)
    t[:3, 3] = node.translation or (0, 0, 0)
    x, y, z, w = node.rotation or (0, 0, 0, 1)
    r = np.eye(4)
    r[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    s = np.diag([*(node.scale or (1, 1, 1)), 1.0])
    return t @ r @ s


def _rest_pose_oracle(path):
    """Every skinned primitive's points in the nodes' rest pose (glTF 2.0 §3.7.3), in the order
    the loader names them (skinned nodes in index order, primitives in order)."""
    gltf = pygltflib.GLTF2().load(str(path))
    parent = {c: i for i, n in enumerate(gltf.nodes) for c in (n.children or [])}

    def world(i):
        m = _local(gltf.nodes[i])
        return world(parent[i]) @ m if i in parent else m

    out = []
    for node in gltf.nodes:
        if node.mesh is None or node.skin is None:
            continue
        skin = gltf.skins[node.skin]
        ibm = _accessor(gltf, skin.inverseBindMatrices, path).reshape(-1, 4, 4).transpose(0, 2, 1)
        joint = np.stack([world(j) for j in skin.joints]) @ ibm
        for prim in gltf.meshes[node.mesh].primitives:
            p = _accessor(gltf, prim.attributes.POSITION, path)
            idx = _accessor(gltf, prim.attributes.JOINTS_0, path).astype(int)
            w = _accessor(gltf, prim.attributes.WEIGHTS_0, path)
            w /= w.sum(axis=1, keepdims=True)
            ph = np.concatenate([p, np.ones((len(p), 1))], axis=1)
            blended = np.einsum("vk,vkij->vij", w, joint[idx])
            out.append(np.einsum("vij,vj->vi", blended, ph)[:, :3])
    return np.concatenate(out)


def _viewer_data(report):
    text = report.read_text(encoding="utf-8")
    config = json.loads(re.search(r'id="dqv-config">(.*?)</script>', text, re.S).group(1))
    blob = base64.b64decode(re.search(r'id="dqv-data">(.*?)</script>', text, re.S).group(1))
    return config["meta"], decode(config["meta"], blob)


@pytest.mark.parametrize("name", SAMPLES)
def test_rest_ghost_in_the_frames_space(shared_assets, tmp_path, name):
    path = shared_assets / "khronos-gltf" / name / SAMPLES[name]
    out = tmp_path / "report"
    result = run_compare(path, out, frames=[0.0], views=("front",), width=16, supersample=1,
                         progress=False, sweeps_dir=None, viewer_frames=2, device="cpu")
    meta, data = _viewer_data(out / "report.html")
    expected = _rest_pose_oracle(path)
    np.testing.assert_allclose(data["rest"], expected, atol=0.51 * meta["step"] + 1e-5)
    # distances are in % of the rest pose's largest extent
    assert result["character_height"] == pytest.approx(np.ptp(expected, axis=0).max(), rel=1e-5)


def test_ties_and_unmeasured_metrics(shared_assets, tmp_path):
    """SimpleSkin (a strip: no closed mesh, no ring to measure) has no value for any metric:
    the summary says why instead of empty rows; every metric where the methods tie is shown as
    a tie and picks no worst frame."""
    out = tmp_path / "simple"
    result = run_compare(shared_assets / "khronos-gltf" / "SimpleSkin" / "SimpleSkin.gltf", out,
                         views=("front",), width=16, supersample=1, progress=False,
                         sweeps_dir=None, viewer_frames=0, device="cpu")
    lines = summary_lines(result)
    assert len(lines) == 3 and all("not measured (" in line for line in lines), lines
    page = (out / "report.html").read_text(encoding="utf-8")
    assert page.count("not measured: ") == 3
    assert "worst volume ratio" not in page and "worst min section" not in page

    # A metric tied by every method: "tie" with both leaders, and no worst frame for it.
    out = tmp_path / "figure"
    result = run_compare(shared_assets / "khronos-gltf" / "RiggedFigure" / "RiggedFigure.glb",
                         out, views=("front",), width=16, supersample=1, progress=False,
                         sweeps_dir=None, viewer_frames=0, device="cpu")
    s = result["summary"]
    tied = [k for k, v in s.items() if v["winner"] == "tie"]
    assert tied, s
    for k in tied:
        values = [r["severity"] for r in s[k]["by_method"].values()]
        assert max(values) - min(values) <= result["tie"]
        assert s[k]["leaders"] == ["lbs", "dqs"]
    page = (out / "report.html").read_text(encoding="utf-8")
    assert page.count("tie: every method within 0.01") == len(tied)
    for k in tied:
        assert f"worst {k.replace('_', ' ')}" not in page
    assert any(f"{k}: " in line and "best: tie: LBS, DQS within 0.01" in line
               for k in tied for line in summary_lines(result))
