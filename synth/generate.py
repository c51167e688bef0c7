"""``ms3d synth``: write a synthetic campus with ground truth, deterministic from preset and seed.

Layout of ``OUT``::

    mesh/            the UAV/MVS-like mesh, a ContextCapture-style production: metadata.xml (SRS,
                     SRSOrigin) and OBJ + MTL + JPEG atlas per tile in local coordinates,
                     Data/Tile_+000_+000/... (tiny, demo: synth.production); the campus preset
                     writes one folder per
                     generation tile (Tile_+000_+000/...); the coarse mesh is one mvs.obj
    mls/             the MLS scan, one LAZ per vehicle pass (LAS 1.4, RGB, GPS time, EPSG:32650),
                     in a frame perturbed from the mesh frame by a known similarity
    images/          vehicle camera images (pinhole: no lens distortion rendered)
    sparse/0/        their poses as a COLMAP text model (cameras.txt with zero distortion, images.txt),
                     world coordinates of the mesh frame
    truth/           truth_mesh.ply (float64 world), truth_faces.npz (class/building per face),
                     registration.json, defects.json (samples; face indices per tile file in
                     "mesh_faces"), scene.json, manifest.json (sha256 of every file)
    campus.yaml      an ``ms3d run`` config for these inputs
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from storage.atomic import file_sha256, write_bytes_atomic, write_json_atomic
from storage.formats.meshes import write_obj, write_ply
from storage.formats.points import LasChunkWriter, PointChunk

from .frames import apply, asprs_classes, random_registration, similarity, streams  # noqa: F401 (re-exported)
from .presets import SynthPreset, get_preset
from .production import write_colmap_model
from .scene import Mesh, Scene

log = logging.getLogger("ms3d.synth")
IMAGES_IN_THREAD = True  # render the camera images beside the rest (the files are the same either way)

WORLD_ORIGIN = (589_000.0, 2_712_000.0, 15.0)  # UTM zone 50N (Zhangzhou, Fujian), metres
CRS = "EPSG:32650"
VERTICAL_DATUM = "ellipsoidal (WGS 84), synthetic"
LAS_DATE = _dt.date(2026, 1, 1)  # fixed: identical seeds give identical bytes
COLMAP_MODEL = "sparse/0"  # the cameras' COLMAP text model, as a COLMAP project lays it out

# ----------------------------------------------------------------------------------- writers


def _prepare_out(out: Path, overwrite: bool) -> None:
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{out} is not empty; pass --overwrite to replace its contents")
        for p in out.iterdir():
            shutil.rmtree(p) if p.is_dir() else p.unlink()
    out.mkdir(parents=True, exist_ok=True)


def write_mvs_tile(folder: Path, name: str, mvs: Mesh, rng: np.random.Generator) -> Path:
    """OBJ + MTL + atlas PNGs in local coordinates, plus a ContextCapture-style metadata.xml."""
    from .texture import bake_atlas

    uv, atlases, face_atlas = bake_atlas(mvs, rng)
    path = write_obj(folder / f"{name}.obj", mvs.vertices, mvs.faces, uv=uv, texture_images=atlases,
                     face_texture=face_atlas, texture_format="jpg")
    return path


def write_metadata_xml(mesh_root: Path) -> None:
    xml = ("<?xml version=\"1.0\" encoding=\"utf-8\"?>\n<ModelMetadata version=\"1\">\n"
           f"\t<SRS>{CRS}</SRS>\n\t<SRSOrigin>{WORLD_ORIGIN[0]:.3f},{WORLD_ORIGIN[1]:.3f},{WORLD_ORIGIN[2]:.3f}</SRSOrigin>\n"
           "\t<Texture><ColorSource>Visible</ColorSource></Texture>\n</ModelMetadata>\n")
    write_bytes_atomic(mesh_root / "metadata.xml", xml.encode())


def scan_to_laz(scene: Scene, trajs: list, path_for, perturb: np.ndarray, density_scale: float,
                rng: np.random.Generator, stats: dict) -> list[Path]:
    """Simulate the MLS along each trajectory and write one LAZ per trajectory, in the MLS frame."""
    from .mls import MlsParams, simulate_mls, with_density

    params = with_density(MlsParams.vmx450(), density_scale)
    origin = np.asarray(WORLD_ORIGIN)
    paths = []
    for traj in trajs:
        path = path_for(traj)
        with LasChunkWriter(path, crs=CRS, offset=np.round(origin / 1000) * 1000,
                            extra_dims={"pass_id": np.uint8, "scanner_id": np.uint8}) as w:
            w.header.creation_date = LAS_DATE
            t0 = time.perf_counter()
            for ch in simulate_mls(scene, [traj], params, rng):
                stats["rays"] = stats.get("rays", 0) + ch.n_rays
                if not len(ch):
                    continue
                xyz = apply(perturb, ch.xyz) + origin
                w.write(PointChunk(xyz=xyz, rgb=ch.rgb, intensity=ch.intensity, gps_time=ch.gps_time,
                                   classification=asprs_classes(ch.source, ch.face_class),
                                   extra={"pass_id": ch.pass_id.astype(np.uint8), "scanner_id": ch.scanner_id.astype(np.uint8)}))
                stats["points"] = stats.get("points", 0) + len(ch)
            stats["scan_seconds"] = stats.get("scan_seconds", 0.0) + time.perf_counter() - t0
        paths.append(path)
    return paths


def write_campus_yaml(out: Path, preset: SynthPreset, mesh_inputs: list[str], seed: int, cameras: bool = False
                      ) -> None:
    """campus.yaml: the mesh is placed by ``mesh/metadata.xml`` (no ``mesh_offset``); with ``cameras``, the
    images and their COLMAP model are inputs."""
    inputs = {"mesh": mesh_inputs, "points": ["mls"], "crs": CRS, "labels": "truth/defects.json"}
    if cameras:
        inputs.update(images="images", cameras=COLMAP_MODEL)
    cfg = {
        "name": f"synth-{preset.name}",
        "work_dir": f"../ms3d-work/synth-{preset.name}-s{seed}",
        "inputs": inputs,
        # the perturbation's prior (random_registration): scale within 0.4 %, and yaw 3 deg about the frame
        # origin plus 2.5 m moves points up to ~6 % of their distance from it, plus 3 m
        "registration": {"max_scale_error": 0.005,
                         "max_displacement_m": round(3.0 + 0.06 * float(np.hypot(*preset.extent_m)), 1)},
    }
    write_bytes_atomic(out / "campus.yaml", yaml.safe_dump(cfg, sort_keys=False).encode())


def write_manifest(out: Path, meta: dict) -> dict:
    """truth/manifest.json: sha256 and size of every file under ``out`` (except itself)."""
    files = {}
    for p in sorted(out.rglob("*")):
        if p.is_file() and p.name != "manifest.json" and not p.name.startswith("."):
            files[str(p.relative_to(out))] = {"sha256": file_sha256(p), "bytes": p.stat().st_size}
    doc = {"generator": "ms3d.synth", **meta, "files": files}
    write_json_atomic(out / "truth" / "manifest.json", doc)
    return doc


# ----------------------------------------------------------------------------------- generation


def _tile_scene(seed: int, preset: SynthPreset, ix: int, iy: int, n_tiles: int, passages: bool = False) -> Scene:
    """The scene of generation tile (ix, iy): deterministic from (seed, ix, iy) alone; ``passages``: buildings
    get ground-floor through-passages with the preset's ``coarse_passage_p`` (the coarse-mesh campus)."""
    from dataclasses import replace

    from .buildings import DEFAULT_FACADE, make_scene

    rng = np.random.default_rng([seed, 1000 + ix, 1000 + iy])
    x0, y0 = ix * preset.tile_m, iy * preset.tile_m
    extent = (x0, y0, min(x0 + preset.tile_m, preset.extent_m[0]), min(y0 + preset.tile_m, preset.extent_m[1]))
    n_b = int(np.ceil(preset.n_buildings / n_tiles))
    tid = (ix + 1) * 1000 + iy + 1
    facade = replace(DEFAULT_FACADE, passage_p=preset.coarse_passage_p) if passages else DEFAULT_FACADE
    return make_scene(rng, extent, n_b, storeys=preset.storeys, facade=facade, first_building_id=tid * 100,
                      first_occluder_id=tid * 10_000)


def _merge_scenes(scenes: list[Scene]) -> Scene:
    from .scene import Occluders

    return Scene(truth=Mesh.concat([s.truth for s in scenes]),
                 occluders=Occluders(Mesh.concat([s.occluders.mesh for s in scenes if s.occluders])),
                 buildings=[b for s in scenes for b in s.buildings], roads=[r for s in scenes for r in s.roads],
                 extent=scenes[0].extent, meta={})


@dataclass
class _SynthRun:
    """What :func:`generate` carries from tile to tile: the output, the preset, the MLS perturbation, the
    tile grid (nx, ny), the scenes still needed (``cache``) and what accumulates (stats, buildings,
    cameras, the number of defects written to ``defects_part``)."""

    out: Path
    preset: SynthPreset
    seed: int
    perturb: np.ndarray
    nx: int
    ny: int
    stats: dict = field(default_factory=dict)
    buildings: list = field(default_factory=list)
    cameras: list = field(default_factory=list)
    n_defects: int = 0
    cache: dict[tuple[int, int], Scene] = field(default_factory=dict)
    coarse_mesh: bool = False  # write a LoD2-like block model (synth.coarse) instead of the MVS mesh
    pool: object = None  # one thread that renders the camera images beside the rest (or None)
    image_jobs: list = field(default_factory=list)  # per tile, in order: a future or the cameras.json entries

    def images(self, *args) -> None:
        """Render and write one tile's camera images (:func:`_tile_images`) in the image thread (ray casting,
        array work and JPEG coding release the GIL: the demo's synth takes 47 s instead of 60 s on 2 cores),
        or here when :data:`IMAGES_IN_THREAD` is off."""
        if not IMAGES_IN_THREAD:
            self.image_jobs.append(_tile_images(*args))
            return
        if self.pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self.pool = ThreadPoolExecutor(1, thread_name_prefix="synth-images")
        self.collect_images()  # at most one tile pending: its scene is the only one the thread keeps alive
        self.image_jobs.append(self.pool.submit(_tile_images, *args))

    def collect_images(self) -> None:
        """Wait for the image thread; the cameras.json entries go to ``cameras`` in tile order."""
        for job in self.image_jobs:
            self.cameras += job if isinstance(job, list) else job.result()
        self.image_jobs.clear()

    @property
    def defects_part(self) -> Path:
        return self.out / "truth" / ".defects.part"  # one JSON array body per tile: memory stays per tile

    def scene_at(self, ix: int, iy: int) -> Scene:
        if (ix, iy) not in self.cache:
            self.cache[(ix, iy)] = _tile_scene(self.seed, self.preset, ix, iy, self.nx * self.ny,
                                               passages=self.coarse_mesh)
        return self.cache[(ix, iy)]


def generate(preset: str = "tiny", seed: int = 0, out: str | Path = "synth-out", overwrite: bool = False,
             scale: float = 1.0, mls_density: float | None = None, coarse_mesh: bool = False) -> Path:
    """Generate a synthetic campus into ``out``; returns ``out``. See the module docstring.

    mls_density: the MLS scanner rate as a fraction of the real one (1.0 = real density); None keeps
    the preset's (demo 0.1). coarse_mesh: the mesh is a LoD2-like block model of the buildings
    (:mod:`synth.coarse`; defects.json labels where the truth departs from it) and the MLS is
    co-registered with it (identity registration), as a city model and a georeferenced scan are; its truth
    buildings get ground-floor through-passages (the preset's ``coarse_passage_p``) the block model lacks."""
    p = get_preset(preset, scale, mls_density)
    out = Path(out).absolute()
    _prepare_out(out, overwrite)
    t_start = time.perf_counter()
    r_reg, = streams(seed, 1)
    truth_reg = random_registration(r_reg)  # MLS local -> mesh local
    if coarse_mesh:
        truth_reg = np.eye(4)
    perturb = np.linalg.inv(truth_reg)  # mesh local -> MLS local
    nx, ny = int(np.ceil(p.extent_m[0] / p.tile_m)), int(np.ceil(p.extent_m[1] / p.tile_m))
    run = _SynthRun(out, p, seed, perturb, nx, ny, coarse_mesh=coarse_mesh)
    run.defects_part.parent.mkdir(parents=True, exist_ok=True)
    try:
        for ix in range(nx):
            for iy in range(ny):
                _write_tile(run, ix, iy)
                # bounded memory: forget scenes no later tile needs
                for key in [k for k in run.cache if k[0] < ix - 1]:
                    del run.cache[key]
        run.collect_images()
    finally:
        if run.pool is not None:
            run.pool.shutdown(cancel_futures=True)
    _write_campus_files(run, truth_reg, scale)
    log.info("synth %s seed %d: %s in %.1f s", p.name, seed, run.stats, time.perf_counter() - t_start)
    return out


def _write_tile(run: _SynthRun, ix: int, iy: int) -> None:
    """Tile (ix, iy): its MVS mesh and defects, its truth mesh, the MLS strips and camera images of its
    roads (scanned against the tile and its neighbours: rays cross tile borders). The images are rendered
    in another thread meanwhile (each part draws from its own random stream, so the files do not depend on
    the order)."""
    from .mvs import MvsParams, make_mvs_mesh
    from .production import defect_faces_by_file, write_production
    from .trajectory import TrajectoryParams, build_trajectories

    out, p, nx, ny, stats = run.out, run.preset, run.nx, run.ny, run.stats
    origin = np.asarray(WORLD_ORIGIN)
    r_mvs, r_tex, r_traj, r_mls, r_cam = streams(run.seed * 7919 + ix * 131 + iy + 1, 5)
    scene = run.scene_at(ix, iy)
    neigh = [run.scene_at(jx, jy) for jx in range(max(ix - 1, 0), min(ix + 2, nx))
             for jy in range(max(iy - 1, 0), min(iy + 2, ny))] if p.tiled_mesh else [scene]
    seen = _merge_scenes(neigh) if len(neigh) > 1 else scene
    tp = TrajectoryParams(n_passes=p.n_passes, gps_start_s=302_400.0 + (ix * ny + iy) * 3600.0)
    trajs = build_trajectories(scene.roads, tp, r_traj, truth=seen.truth)
    if p.image_every_m > 0:
        run.images(out / "images", seen, trajs, p.image_every_m, p.image_size, r_cam, origin, f"{ix:02d}{iy:02d}_")
    name = f"Tile_{ix:+04d}_{iy:+04d}" if p.tiled_mesh else "mvs"
    if run.coarse_mesh:
        from .coarse import make_coarse_mesh

        mvs, tile_defects = make_coarse_mesh(scene)
    else:
        mvs, tile_defects = make_mvs_mesh(r_mvs, scene, MvsParams(edge_facade_m=p.mvs_edge_m))
    production = _production_tile_m(run) if not run.coarse_mesh else 0.0
    if production:
        tiles = write_production(out / "mesh", mvs, production, r_tex, lod_tile=p.lod_tile)
    else:
        write_mvs_tile(out / "mesh" / name if p.tiled_mesh else out / "mesh", name, mvs, r_tex)
    for d in tile_defects:
        d["id"] = f"{ix}_{iy}_{d['id']}"
        if production:  # face indices per tile file: {"mesh/Data/Tile_.../Tile_....obj": [...]}
            d["mesh_faces"] = defect_faces_by_file(d.pop("faces", []), tiles)
        else:
            d["mesh_file"] = f"mesh/{name}/{name}.obj" if p.tiled_mesh else "mesh/mvs.obj"
    with open(run.defects_part, "a") as fp:
        for d in tile_defects:
            fp.write((",\n" if run.n_defects else "") + json.dumps(d, indent=None, default=_json_default))
            run.n_defects += 1
    del tile_defects
    stats["mvs_faces"] = stats.get("mvs_faces", 0) + mvs.n_faces
    tname = f"truth_mesh_{name}" if p.tiled_mesh else "truth_mesh"
    write_ply(out / "truth" / f"{tname}.ply", scene.truth.vertices + origin, scene.truth.faces,
              face_colors=scene.truth.face_color)
    _save_npz(out / "truth" / f"{tname}_faces.npz", face_class=scene.truth.face_class,
              face_building=scene.truth.face_building)
    run.buildings += [_building_json(b, d) for b, d in zip(scene.buildings, scene.meta["buildings"])]
    scan_to_laz(seen, trajs, lambda t: out / "mls" / f"strip_{ix:02d}{iy:02d}_{t.traj_id:03d}.laz",
                run.perturb, p.mls_density_scale, r_mls, stats)


def _tile_images(folder: Path, scene: Scene, trajs: list, every_m: float, size, rng, origin, prefix: str) -> list:
    """Render and write a tile's camera images (``synth.cameras``); returns their cameras.json entries."""
    from .cameras import render_cameras, write_images

    imgs, cams = render_cameras(scene, trajs, every_m=every_m, size=size, rng=rng)
    return write_images(folder, imgs, cams, None, origin, prefix=prefix)


def _production_tile_m(run: _SynthRun) -> float:
    """The production tile grid (0: no production): the preset's, or the generation tile when the campus
    has several generation tiles and the preset's grid does not divide them (tiles would collide)."""
    p = run.preset
    if p.tiled_mesh or p.production_tile_m <= 0:
        return 0.0
    if run.nx * run.ny == 1 or float(p.tile_m / p.production_tile_m).is_integer():
        return p.production_tile_m
    return p.tile_m


def _write_campus_files(run: _SynthRun, truth_reg: np.ndarray, scale: float) -> None:
    """What follows the tiles: metadata.xml, cameras.json, registration.json, defects.json, scene.json,
    campus.yaml and the manifest (last: it hashes every file)."""
    out, p, seed = run.out, run.preset, run.seed
    mesh_inputs = ["mesh"]
    write_metadata_xml(out / "mesh")
    if run.cameras:  # the mesh frame, world coordinates: what the photogrammetry delivers
        write_colmap_model(out / COLMAP_MODEL, run.cameras, WORLD_ORIGIN)
    write_json_atomic(out / "truth" / "registration.json", {
        "frame_origin": list(WORLD_ORIGIN), "crs": CRS,
        "matrix_mls_to_mesh": truth_reg.tolist(),
        "note": "mesh_world - frame_origin = M (mls_world - frame_origin); M = [s R | t]",
    })
    _assemble_defects(out / "truth" / "defects.json", run.defects_part)
    write_json_atomic(out / "truth" / "scene.json", {"preset": p.name, "seed": seed, "scale": scale,
                                                     "mls_density": p.mls_density_scale,
                                                     **({"coarse_mesh": True} if run.coarse_mesh else {}),
                                                     "extent_m": list(p.extent_m), "buildings": run.buildings,
                                                     "stats": {k: v for k, v in run.stats.items() if k != "scan_seconds"}})
    write_campus_yaml(out, p, mesh_inputs, seed, bool(run.cameras))
    write_manifest(out, {"preset": p.name, "seed": seed, "scale": scale, "mls_density": p.mls_density_scale})


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def _assemble_defects(path: Path, part: Path) -> None:
    """defects.json from the per-tile fragments, streamed (atomically), then drop the fragments."""
    from storage.atomic import atomic_path

    head = json.dumps({"frame_origin": list(WORLD_ORIGIN), "frame": "mesh"})[:-1] + ', "defects": [\n'
    with atomic_path(path) as tmp, open(tmp, "w") as out:
        out.write(head)
        if part.exists():
            with open(part) as src:
                shutil.copyfileobj(src, out, 1 << 22)
        out.write("\n]}\n")
    part.unlink(missing_ok=True)


def _save_npz(path: Path, **arrays) -> None:
    import io

    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    write_bytes_atomic(path, buf.getvalue())


def _building_json(b, info: dict) -> dict:
    """scene.json's record of one building; with a through-passage, its "passage" (``synth.passages``)."""
    return {"id": int(b.id), "footprint": np.asarray(b.footprint).round(4).tolist(), "storeys": int(b.storeys),
            "storey_height_m": float(b.storey_height_m), "roof": b.roof, "eave_overhang_m": float(b.eave_overhang_m),
            "height_m": float(b.height_m), **({"passage": info["passage"]} if info.get("passage") else {})}
