"""Implicit tiling (export.tiling: implicit): the subtree format, the availability bits against the explicit
quadtree, and the tiny export written as implicit tiles (same glbs, checks passing, switching back and forth
rebuilding nothing)."""

from __future__ import annotations

import json
import shutil
import struct

import numpy as np
import pytest

from storage.errors import InputError
from storage.formats.subtree import Subtree, decode_subtree, encode_subtree, level_offset, morton2
from tasks.config import ExportConfig
from tasks.export import run_export
from tasks.export.check import check_mesh_features, check_tileset, node_tools, validate_glbs
from tasks.export.georef import gltf_to_enu
from tasks.export.gltf import glb_positions
from tasks.export.implicit import (
    SUBTREE_URI,
    build_subtrees,
    derived_box,
    expand_implicit,
    implicit_coords,
    root_geometric_error,
    template,
)
from tasks.export.tree import plan_quadtree

TILES = ["0_0", "1_0", "5_1", "6_6", "7_7", "3_4", "2_7"]  # a sparse 8 x 8 tile square: height 3, 4 levels


def _records(tree) -> dict[str, dict]:
    """Made-up node records: a distinct box per node (its key in the centre) and errors growing per level."""
    out = {}
    for h, level in enumerate(tree.levels):
        for i, n in enumerate(level):
            out[n.key] = {"box": [n.x, n.y, h, 1, 0, 0, 0, 1, 0, 0, 0, 1 + i], "geometricError": 0.3 * h * (1 + i % 2),
                          "uri": f"content/{n.key}.glb"}
    return out


def test_morton_order_and_bitstream_layout():
    assert morton2(np.arange(4), np.zeros(4, int)).tolist() == [0, 1, 4, 5]  # x on the even bits
    assert morton2(0, np.arange(4)).tolist() == [0, 2, 8, 10]
    assert [level_offset(k) for k in range(4)] == [0, 1, 5, 21]
    tiles = np.zeros(21, bool)
    tiles[[0, 2, 5 + 6]] = True  # the root, its child (1, 0) and that child's child (3, 1): Morton 6 on level 2
    data = encode_subtree(Subtree(tiles, tiles.copy(), np.zeros(64, bool)))
    magic, version, n_json, n_bin = struct.unpack_from("<4sIQQ", data)
    assert (magic, version) == (b"subt", 1) and n_json % 8 == 0 and n_bin % 8 == 0 and len(data) == 24 + n_json + n_bin
    doc = json.loads(data[24 : 24 + n_json])
    assert doc["childSubtreeAvailability"] == {"constant": 0}
    view = doc["bufferViews"][doc["tileAvailability"]["bitstream"]]
    raw = data[24 + n_json + view["byteOffset"] : 24 + n_json + view["byteOffset"] + view["byteLength"]]
    assert raw == bytes([0b00000101, 0b00001000, 0])  # bits 0, 2 and 11, least significant first
    assert doc["tileAvailability"]["availableCount"] == 3
    full = encode_subtree(Subtree(np.ones(5, bool), np.ones(5, bool), np.ones(16, bool)))
    assert json.loads(full[24:].split(b"}}", 1)[0] + b"}}")["tileAvailability"] == {"constant": 1}


def test_a_malformed_subtree_is_one_line_naming_it():
    with pytest.raises(InputError, match=r"a/0/0/0\.subtree: not a version 1 binary subtree"):
        decode_subtree(b"glTF" + bytes(30), 2, "a/0/0/0.subtree")
    with pytest.raises(InputError, match="truncated"):
        decode_subtree(encode_subtree(Subtree(np.ones(5, bool), np.ones(5, bool), np.zeros(16, bool)))[:30], 2, "b")


@pytest.mark.parametrize("subtree_levels", [1, 2, 4])
def test_subtree_bits_match_the_explicit_tree(subtree_levels):
    tree = plan_quadtree(TILES)
    nodes = _records(tree)
    coords = implicit_coords(tree)
    present = set(coords.values())
    subtrees = build_subtrees(tree, nodes, subtree_levels)
    files = {template(SUBTREE_URI, c): encode_subtree(sub, "tile") for c, sub in subtrees.items()}
    assert all(c[0] % subtree_levels == 0 for c in subtrees)
    for l0, x0, y0 in subtrees:  # every bit, decoded, against the tree
        back = decode_subtree(files[template(SUBTREE_URI, (l0, x0, y0))], subtree_levels)
        for d in range(subtree_levels):
            for lx in range(2**d):
                for ly in range(2**d):
                    bit = level_offset(d) + int(morton2(lx, ly))
                    want = (l0 + d, (x0 << d) + lx, (y0 << d) + ly) in present
                    assert back.tiles[bit] == want and back.content[bit] == want
        for lx in range(2**subtree_levels):
            for ly in range(2**subtree_levels):
                want = (l0 + subtree_levels, (x0 << subtree_levels) + lx, (y0 << subtree_levels) + ly) in present
                assert back.children[int(morton2(lx, ly))] == want
    # expanded back into explicit tiles: the same tree, each node's own box and error from the tile metadata
    doc = {"asset": {"version": "1.1"}, "geometricError": 9.0,
           "root": {"boundingVolume": {"box": [4, 4, 0, 4, 0, 0, 0, 4, 0, 0, 0, 1]}, "refine": "REPLACE",
                    "geometricError": root_geometric_error(tree, nodes), "content": {"uri": "c/{level}/{x}/{y}.glb"},
                    "implicitTiling": {"subdivisionScheme": "QUADTREE", "subtreeLevels": subtree_levels,
                                       "availableLevels": len(tree.levels), "subtrees": {"uri": SUBTREE_URI}}}}
    by_coord = {c: n for n, c in coords.items()}

    def walk(t):
        c = tuple(t["implicit"]["coord"])
        n = by_coord[c]
        assert t["boundingVolume"]["box"] == nodes[n.key]["box"]
        assert t["geometricError"] == nodes[n.key]["geometricError"] <= doc["root"]["geometricError"] / 2 ** c[0]
        assert t["content"]["uri"] == f"c/{c[0]}/{c[1]}/{c[2]}.glb"
        kids = sorted(by_coord[tuple(k["implicit"]["coord"])] for k in t.get("children", []))
        assert kids == sorted(tree.children.get(n, []))
        return 1 + sum(walk(k) for k in t.get("children", []))

    assert walk(expand_implicit(doc, files.__getitem__)["root"]) == len(coords)


def test_derived_boxes_tile_the_root():
    root = [10.0, 20.0, 5.0, 8.0, 0.0, 0.0, 0.0, 8.0, 0.0, 0.0, 0.0, 3.0]
    boxes = [derived_box(root, (2, x, y)) for x in range(4) for y in range(4)]
    centres = np.array([b[:2] for b in boxes])
    assert sorted(set(centres[:, 0])) == [4.0, 8.0, 12.0, 16.0] and sorted(set(centres[:, 1])) == [14.0, 18.0, 22.0, 26.0]
    assert derived_box(root, (2, 0, 3))[:2] == [4.0, 26.0]  # x east, y north from the south-west corner
    assert all(b[3] == 2.0 and b[7] == 2.0 and b[11] == 3.0 for b in boxes)


def test_availability_breaking_the_rules_is_refused():
    tiles = np.array([1, 0, 1, 0, 0], bool)
    content = np.array([1, 1, 0, 0, 0], bool)  # content on tile (1, 0, 0), which is not available
    files = {"s/0/0/0.subtree": encode_subtree(Subtree(tiles, content, np.zeros(16, bool)))}
    doc = {"root": {"boundingVolume": {"box": [0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1]}, "refine": "REPLACE",
                    "geometricError": 1.0, "content": {"uri": "{level}/{x}/{y}.glb"},
                    "implicitTiling": {"subdivisionScheme": "QUADTREE", "subtreeLevels": 2, "availableLevels": 2,
                                       "subtrees": {"uri": "s/{level}/{x}/{y}.subtree"}}}}
    with pytest.raises(InputError, match="content available where its tile is not"):
        expand_implicit(doc, files.__getitem__)


def _tiles(work) -> list[str]:
    return sorted(p.name for p in (work / "tiles").iterdir() if (p / "merged.json").exists())


@pytest.fixture(scope="module")
def implicit_export(tiny_merged, tmp_path_factory):
    work = tmp_path_factory.mktemp("implicit") / "work"
    shutil.copytree(tiny_merged, work)
    return work, run_export(work, ExportConfig(tiling="implicit", subtree_levels=2))


def test_implicit_export_moves_the_same_glbs_and_passes_the_checks(tiny_export, implicit_export):
    work, summary = implicit_export
    out, explicit_out = work / "output", tiny_export[0] / "output"
    doc = json.loads((out / "tileset.json").read_text())
    imp = doc["root"]["implicitTiling"]
    assert imp == {"subdivisionScheme": "QUADTREE", "subtreeLevels": 2, "availableLevels": 3,
                   "subtrees": {"uri": "subtrees/{level}/{x}/{y}.subtree"}}
    assert doc["root"]["content"] == {"uri": "content/{level}/{x}/{y}.glb"} and "children" not in doc["root"]
    assert check_tileset(out) == []
    # every explicit node's glb, byte for byte, at its implicit path: 3 x 2 tiles of 25 m, height 2
    tree = plan_quadtree(_tiles(work))
    leaves = [f"subtrees/2/{n.x}/{n.y}.subtree" for n in tree.levels[0]]  # two levels a subtree: one per leaf
    assert sorted(p.relative_to(out).as_posix() for p in (out / "subtrees").rglob("*.subtree")) == sorted(
        ["subtrees/0/0/0.subtree", *leaves])
    explicit = json.loads((explicit_out / "tileset.fingerprints.json").read_text())["nodes"]
    state = json.loads((out / "tileset.fingerprints.json").read_text())["nodes"]
    for n, (level, x, y) in implicit_coords(tree).items():
        assert state[n.key]["uri"] == f"content/{level}/{x}/{y}.glb"
        assert (out / state[n.key]["uri"]).read_bytes() == (explicit_out / explicit[n.key]["uri"]).read_bytes()
    assert not (out / "content" / "tiles").exists() and not (out / "content" / "lod1").exists()
    for glb in sorted((out / "content").rglob("*.glb")):
        assert check_mesh_features(glb.read_bytes()) == [], glb
    # the derived geometric errors never below the measured ones; leaves within a patch of their square
    full = expand_implicit(doc, lambda rel: (out / rel).read_bytes())
    overhang = []

    def walk(t):
        level = t["implicit"]["coord"][0]
        assert t["geometricError"] <= doc["root"]["geometricError"] / 2**level + 1e-12
        if "children" not in t:
            pos = gltf_to_enu(glb_positions((out / t["content"]["uri"]).read_bytes()))
            b = np.asarray(t["implicit"]["box"])
            local = np.abs((pos - b[:3]) @ (b[3:9].reshape(2, 3) / np.linalg.norm(b[3:9].reshape(2, 3), axis=1)[:, None]).T)
            overhang.append(float((local - np.linalg.norm(b[3:9].reshape(2, 3), axis=1)).max()))
        for k in t.get("children", []):
            walk(k)

    walk(full["root"])
    print(f"leaves overhang their derived boxes by at most {max(overhang):.2f} m; root geometricError "
          f"{doc['root']['geometricError']:.3f} m")
    assert len(overhang) == 6 and max(overhang) < 2.5, overhang  # at most about a patch (2.3 m) over the edge
    assert summary["tiling"] == "implicit" and summary["archive"] is None


def test_switching_tiling_rebuilds_nothing_and_gives_the_explicit_tileset_back(tiny_export, implicit_export, tmp_path):
    work = tmp_path / "work"
    shutil.copytree(implicit_export[0], work)
    out = work / "output"
    subtrees = {p.name: p.read_bytes() for p in (out / "subtrees").rglob("*.subtree")}
    back = run_export(work, ExportConfig(tiling="explicit"))
    assert back["built"] == [] and not (out / "subtrees").exists()
    assert (out / "tileset.json").read_bytes() == (tiny_export[0] / "output" / "tileset.json").read_bytes()
    assert check_tileset(out) == []
    again = run_export(work, ExportConfig(tiling="implicit", subtree_levels=2))
    assert again["built"] == [] and check_tileset(out) == []
    assert {p.name: p.read_bytes() for p in (out / "subtrees").rglob("*.subtree")} == subtrees
    # tiles 2_0 and 2_1 gone: the tree one level lower (and a new ENU centre: every node rebuilt), every node's
    # implicit path a level up, over the old ones; nothing stale left
    for t in ("2_0", "2_1"):
        shutil.rmtree(work / "tiles" / t)
    lower = run_export(work, ExportConfig(tiling="implicit", subtree_levels=2))
    state = _state(out)
    assert sorted(lower["built"]) == sorted(state) == ["L0_0_0", "L0_0_1", "L0_1_0", "L0_1_1", "L1_0_0"]
    assert state["L0_0_0"]["uri"] == "content/1/0/0.glb" and state["L1_0_0"]["uri"] == "content/0/0/0.glb"
    assert check_tileset(out) == []
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*.glb") if "content" in p.parts) == sorted(
        r["uri"] for r in state.values())
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*.subtree")) == [
        "subtrees/0/0/0.subtree"]  # two levels: one subtree


def _state(out) -> dict[str, dict]:
    return json.loads((out / "tileset.fingerprints.json").read_text())["nodes"]


def test_implicit_glbs_pass_the_gltf_validator(implicit_export):
    node, reason = node_tools()
    if node is None:
        pytest.fail(reason)
    out = implicit_export[0] / "output"
    reports = validate_glbs(sorted(out.rglob("*.glb")))
    assert len(reports) == 6 + 2 + 1 + 1 and all(r["errors"] == 0 for r in reports), [r["messages"] for r in reports]


def test_a_tile_orphaned_in_its_subtree_is_refused():
    tiles = np.array([1, 0, 0, 0, 0, 1, 0, 0, 0] + [0] * 12, bool)  # level-2 tile (0, 0) under a missing (1, 0, 0)
    files = {"s/0/0/0.subtree": encode_subtree(Subtree(tiles, tiles.copy(), np.zeros(64, bool)))}
    doc = {"root": {"boundingVolume": {"box": [0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1]}, "refine": "REPLACE",
                    "geometricError": 1.0, "content": {"uri": "{level}/{x}/{y}.glb"},
                    "implicitTiling": {"subdivisionScheme": "QUADTREE", "subtreeLevels": 3, "availableLevels": 3,
                                       "subtrees": {"uri": "s/{level}/{x}/{y}.subtree"}}}}
    with pytest.raises(InputError, match=r"s/0/0/0\.subtree: 1 available tiles have no available parent"):
        expand_implicit(doc, files.__getitem__)


def test_moving_content_onto_each_others_paths_loses_nothing(tmp_path):
    from tasks.export.stage import _place_content

    for rel, data in (("content/1/0/0.glb", b"A"), ("content/2/0/0.glb", b"B")):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(data)
    nodes = {"a": {"uri": "content/1/0/0.glb", "built_uri": "content/lod1/0_0.glb"},
             "b": {"uri": "content/2/0/0.glb", "built_uri": "content/tiles/0_0.glb"}}
    placed = _place_content(tmp_path, nodes, {"a": "content/2/0/0.glb", "b": "content/3/0/0.glb"})
    assert (tmp_path / "content/2/0/0.glb").read_bytes() == b"A" and (tmp_path / "content/3/0/0.glb").read_bytes() == b"B"
    assert placed["a"] == {"uri": "content/2/0/0.glb", "built_uri": "content/lod1/0_0.glb"}
    back = _place_content(tmp_path, placed, None)  # explicit: back where the builds wrote them
    assert back == {"a": {"uri": "content/lod1/0_0.glb"}, "b": {"uri": "content/tiles/0_0.glb"}}
    assert (tmp_path / "content/lod1/0_0.glb").read_bytes() == b"A" and not (tmp_path / "content/2/0/0.glb").exists()


def test_export_check_finds_the_implicit_leaves_for_the_ecef_round_trip(implicit_export, capsys):
    from tasks.export.check import leaf_glbs, main

    work, _ = implicit_export
    leaves = leaf_glbs(work / "output")
    assert sorted(leaves) == _tiles(work) and all(p.exists() and "tiles" not in p.parts for p in leaves.values())
    code = main([str(work)])
    report = json.loads(capsys.readouterr().out)
    assert report["ecef_round_trip_max_mm"] is not None and report["ecef_round_trip_max_mm"] < 1.0
    assert report["tileset_problems"] == [] and code == 0
