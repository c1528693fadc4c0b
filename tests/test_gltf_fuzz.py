"""Mutated glTF input never escapes as anything but a one-line VbusdError (deterministic fuzzing).

Mutations: JSON values of bar.gltf replaced by values of the wrong type or range, or deleted
(1-3 per file); bytes of bar.glb overwritten (header, JSON and BIN chunks) or the file cut short.
Earlier runs of this harness found empty ``attributes`` objects and ``null`` samplers reaching the
converter as raw Python values; both are now reported with their JSON pointer.
"""

from __future__ import annotations

import copy
import json
import random
from pathlib import Path

import pytest

from vbusd.converters import gltf
from vbusd.format.errors import VbusdError

FIXTURES = Path(__file__).parent / "fixtures" / "gltf"
VALUES = [None, -1, 0, 1, 2, 3, 7, 10 ** 12, 1.5, "x", "", [], {}, [1, 2], True, 1e308,
          [0] * 16, "CUBICSPLINE", "STEP", "rotation", "weights"]


def _paths(value, path=()):
    yield path
    if isinstance(value, dict):
        for key, child in value.items():
            if key != "uri":
                yield from _paths(child, path + (key,))
    elif isinstance(value, list):
        for index, child in enumerate(value):
            yield from _paths(child, path + (index,))


def _read_expecting_vbusd_error_or_success(path: Path) -> None:
    try:
        gltf.read(path)
    except VbusdError as error:
        assert "\n" not in str(error)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(4))
def test_json_mutations(tmp_path, seed):
    base = json.loads((FIXTURES / "bar.gltf").read_text())
    paths = list(_paths(base))[1:]
    rng = random.Random(seed)
    target = tmp_path / "mutated.gltf"
    for _ in range(30):
        doc = copy.deepcopy(base)
        for _ in range(rng.randint(1, 3)):
            path = rng.choice(paths)
            try:
                parent = doc
                for key in path[:-1]:
                    parent = parent[key]
                if rng.random() < 0.15 and isinstance(parent, dict):
                    del parent[path[-1]]
                else:
                    parent[path[-1]] = rng.choice(VALUES)
            except (KeyError, IndexError, TypeError):
                pass
        target.write_text(json.dumps(doc))
        _read_expecting_vbusd_error_or_success(target)


@pytest.mark.parametrize("seed", range(4))
def test_glb_byte_mutations(tmp_path, seed):
    base = (FIXTURES / "bar.glb").read_bytes()
    rng = random.Random(1000 + seed)
    target = tmp_path / "mutated.glb"
    for _ in range(30):
        data = bytearray(base)
        for _ in range(rng.randint(1, 4)):
            index = rng.randrange(len(data)) if rng.random() < 0.7 else rng.randrange(64)
            data[index] = rng.randrange(256)
        if rng.random() < 0.1:
            data = data[:rng.randrange(len(data))]
        target.write_bytes(bytes(data))
        _read_expecting_vbusd_error_or_success(target)
