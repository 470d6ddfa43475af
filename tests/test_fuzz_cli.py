"""Seeded fuzzing of the CLI with corrupted copies of the shared real assets.

Every mutation (truncation, bit flips, damaged counts, offsets and strides) must end as either a
normal run (exit 0, the output written) or a refusal (exit 2, one ``dqskin: error:`` line, no
traceback), and never leave a temporary or partial file behind. Bounded: a fixed number of
mutations per asset, small frame ranges.
"""

import json
import random
import re
import time

from dqskin.cli import main

ASSETS = ["khronos-gltf/RiggedSimple/RiggedSimple.glb", "khronos-gltf/SimpleSkin/SimpleSkin.gltf",
          "usd-wg/CesiumMan/CesiumMan.usdz", "tinyusdz/skintest.usda", "tinyusdz/skintest.usdc"]
CASES_PER_ASSET = 12
BUDGET_SECONDS = 90


def _mutate_bytes(data, rng):
    data = bytearray(data)
    kind = rng.choice(["truncate", "flip", "zero"])
    if kind == "truncate":
        return bytes(data[:rng.randrange(1, len(data))])
    for _ in range(rng.randint(1, 16)):
        i = rng.randrange(len(data))
        data[i] = (data[i] ^ (1 << rng.randrange(8))) if kind == "flip" else 0
    return bytes(data)


_NUMBER = re.compile(rb'("(?:count|byteOffset|byteStride|byteLength|bufferView|componentType)"'
                     rb'\s*:\s*)(\d+)')


def _mutate_gltf_json(text, rng):
    """Damage a count/offset/stride/index field of a .gltf document."""
    fields = list(_NUMBER.finditer(text))
    if not fields:
        return _mutate_bytes(text, rng)
    m = rng.choice(fields)
    value = rng.choice([b"0", b"1", b"3", b"-1", b"999999999", b"2147483647"])
    return text[:m.start(2)] + value + text[m.end(2):]


_USDA_ARRAY = re.compile(rb"\[[-0-9., ()e]+\]")


def _mutate_usda(text, rng):
    """Drop elements of a numeric array, or damage a number, of a .usda layer."""
    arrays = list(_USDA_ARRAY.finditer(text))
    if arrays and rng.random() < 0.6:
        m = rng.choice(arrays)
        items = m.group(0)[1:-1].split(b",")
        keep = items[:rng.randrange(len(items))] if len(items) > 1 else [b"nan"]
        return text[:m.start()] + b"[" + b",".join(keep) + b"]" + text[m.end():]
    return _mutate_bytes(text, rng)


def _cases(shared_assets):
    rng = random.Random(20261201)
    for rel in ASSETS:
        src = shared_assets / rel
        if not src.is_file():
            continue
        data = src.read_bytes()
        for k in range(CASES_PER_ASSET):
            if src.suffix == ".gltf":
                mutated = _mutate_gltf_json(data, rng)
            elif src.suffix == ".usda":
                mutated = _mutate_usda(data, rng)
            else:
                mutated = _mutate_bytes(data, rng)
            yield src, f"{src.stem}_{k}{src.suffix}", mutated


def test_corrupted_assets_fail_cleanly(shared_assets, tmp_path, capsys):
    start = time.monotonic()
    outcomes = {}
    cases = list(_cases(shared_assets))
    assert len(cases) >= 2 * CASES_PER_ASSET, "shared assets missing"
    for src, name, data in cases:
        case = tmp_path / name.replace(".", "_")
        case.mkdir()
        for sibling in src.parent.iterdir():  # external buffers and textures of .gltf files
            if sibling.is_file() and sibling != src and sibling.suffix in (".bin", ".png", ".jpg"):
                (case / sibling.name).symlink_to(sibling)
        bad = case / src.name
        bad.write_bytes(data)
        out = case / "out" / "cache.npz"
        rc = main(["skin", str(bad), "--out", str(out), "--frames", "0:2"
                   if src.suffix in (".usda", ".usdz") else "0:0.1:0.05"])
        err = capsys.readouterr().err
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert rc in (0, 2), (name, rc, err)
        assert "Traceback" not in err, (name, err)
        if rc == 2:
            assert len(lines) == 1 and lines[0].startswith("dqskin: error:"), (name, err)
        leftovers = [p.name for p in (case / "out").glob("*")] if (case / "out").exists() else []
        assert leftovers == (["cache.npz"] if rc == 0 else []), (name, leftovers)
        assert bad.read_bytes() == data, f"{name}: the input was modified"
        outcomes[name] = rc
        assert time.monotonic() - start < BUDGET_SECONDS, "fuzzing ran past its time budget"
    assert 2 in outcomes.values(), json.dumps(outcomes)
