"""The simulator's design choices in docs/SIM.md, re-measured in one run on this machine:
physics sub-steps (trajectories against 240 and 960 Hz, the physics' cost a tick), the time
of ``reset()``, the checker floor as two plain meshes against the same checker as a texture,
one floor quad against the small triangles, PyBullet's EGL renderer against TinyRenderer, the
floor texture's size (256 against 512 texels) and where its BMP is written, TinyRenderer's
shadow map, and the camera look's cost.

    python benchmarks/bench_sim_choices.py [--rounds 10] [--out benchmarks/results]

Renders are pinhole (the image PyBullet draws; the fisheye, the default lens, renders a wider
pinhole and warps it). Timed variants are interleaved in rounds, each round in a rotated
order, so a drift in the machine's load falls on all alike; the figures are medians of wall
times. Writes sim_choices.json and sim_choices.md to --out.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import math
import os
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from bench_sim import machine
from versions import run_record, write_results

from jetbot_rt.sim import appearance, looks, textures
from jetbot_rt.sim import world as world_module
from jetbot_rt.sim.camera_look import CameraLook
from jetbot_rt.sim.camera_model import CAMERA_ASPECT
from jetbot_rt.sim.config import SimConfig
from jetbot_rt.sim.native_output import pybullet_chatter_filtered
from jetbot_rt.sim.pybullet_import import import_pybullet
from jetbot_rt.sim.world import CAMERA_FAR, CAMERA_NEAR, JetbotWorld, pixel_centred
from jetbot_rt.tasks.scene import Block, Box, Scene

p = import_pybullet()

TICK = 1 / 30
RATES = (960.0, 240.0, 120.0, 60.0, 30.0)
SIZES = (56, 224)
PINHOLE = SimConfig(lens="pinhole")
VIEWS = [  # (robot x, y, yaw), block (x, y): the seed scene and five views across the room
    ((-0.6, 0.0, 0.0), (0.3, 0.0)), ((0.8, 0.5, 2.8), (-0.2, 0.2)),
    ((0.0, -1.0, 1.57), (0.1, 0.2)), ((-1.0, -1.0, 0.79), (0.0, 0.0)),
    ((1.0, -0.8, 2.4), (0.2, 0.3)), ((0.2, 1.1, -1.8), (0.0, 0.0)),
]
SCENES = [Scene(pose, (Block(xy, name="goal"),)) for pose, xy in VIEWS]
BOX = 0.4
"""m: the box whose shadow TinyRenderer's shadow map casts (docs/SIM.md: "a 40 cm box")."""
BOX_SCENES = [  # the box 1 m ahead, seen from four sides; the light comes from -x, +y, above
    Scene((x, y, yaw), (Block((bx, by), name="goal"), Box((0.0, 0.0), (BOX, BOX, BOX))))
    for (x, y, yaw), (bx, by) in (((1.0, 0.0, math.pi), (0.5, -0.3)),
                                  ((0.0, -1.0, math.pi / 2), (0.3, -0.5)),
                                  ((-1.0, 0.0, 0.0), (-0.5, 0.3)),
                                  ((0.7, -0.7, 3 * math.pi / 4), (0.4, -0.1)))
]
LOOK = SimConfig(exposure=1.3, white_balance=[1.1, 1.0, 0.9], gain_noise=0.03, vignetting=0.5,
                 motion_blur=0.02)
"""Every camera-look effect on (bench_appearance.py's "worst" values)."""


def in_rounds(names: list[Any], rounds: int) -> Iterator[Any]:
    """The variants, round after round, each round's order rotated by one."""
    for r in range(rounds):
        k = r % len(names)
        yield from names[k:] + names[:k]


def median_ms(seconds: list[float]) -> float:
    return round(1e3 * float(np.median(seconds)), 3)


# 1. Physics sub-steps ---------------------------------------------------------------------


def duty_runs() -> dict[str, np.ndarray]:
    """tests/test_sim_world.py's duties (the policy-like draw is its seed and clip); the
    straight run lasts 15 s, long enough to reach the block and push it."""
    rng = np.random.default_rng(0)
    return {"straight at duty 0.1 into the block, 15 s": np.full((450, 2), 0.1),
            "policy-like (0.07 +- 0.05 per wheel, new every tick), 10 s":
                np.clip(0.07 + 0.05 * rng.standard_normal((300, 2)), -0.1, 0.1),
            "sustained curve (0.1, 0.05), 10 s": np.tile([0.1, 0.05], (300, 1))}


def trajectory(physics_hz: float, duties: np.ndarray) -> tuple[np.ndarray, float]:
    """The robot's (x, y, yaw) after each 30 Hz tick, and how far it pushed the block (m)."""
    with JetbotWorld(SimConfig(physics_hz=physics_hz), image_size=(8, 8)) as world:
        poses = []
        for left, right in duties:
            world.set_duty(left, right)
            world.step(TICK)
            poses.append(world.robot_pose())
        return np.array(poses), world.block_shift()


def turned_deg(poses: np.ndarray) -> float:
    return math.degrees(np.unwrap(np.concatenate([[0.0], poses[:, 2]]))[-1])


def sub_steps() -> dict[str, dict[str, dict[str, float]]]:
    """Per run and rate: max position / heading difference from 240 Hz, the angle turned."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for name, duties in duty_runs().items():
        runs = {hz: trajectory(hz, duties) for hz in RATES}
        ref = runs[240.0][0]
        out[name] = {}
        for hz, (poses, pushed) in runs.items():
            heading = np.angle(np.exp(1j * (poses[:, 2] - ref[:, 2])))
            out[name][f"{hz:g}"] = {
                # the larger of max |dx| and max |dy|, as the test measures it
                "max_position_mm": round(1e3 * float(np.abs(poses[:, :2] - ref[:, :2]).max()), 2),
                "max_heading_deg": round(math.degrees(float(np.abs(heading).max())), 3),
                "turned_deg": round(turned_deg(poses), 2),
                "turn_ratio_vs_240": round(turned_deg(poses) / turned_deg(ref), 4),
                "block_pushed_mm": round(1e3 * pushed, 1)}
    return out


def physics_cost(rounds: int, ticks: int) -> dict[str, float]:
    """Median ms of ``step(1/30)`` (no render) per rate, policy-like duties."""
    worlds = {hz: JetbotWorld(SimConfig(physics_hz=hz), image_size=(8, 8)) for hz in RATES}
    duties = next(d for n, d in duty_runs().items() if n.startswith("policy"))
    seconds: dict[float, list[float]] = {hz: [] for hz in RATES}
    for hz in in_rounds(list(RATES), rounds):
        world = worlds[hz]
        world.reset()
        for left, right in duties[:ticks]:
            world.set_duty(left, right)
            t = time.perf_counter()
            world.step(TICK)
            seconds[hz].append(time.perf_counter() - t)
    for world in worlds.values():
        world.close()
    return {f"{hz:g}": median_ms(s) for hz, s in seconds.items()}


# 2. reset() ------------------------------------------------------------------------------


def reset_cost(resets: int) -> dict[str, float]:
    """The default world's ``reset()`` (today's [sim] defaults), ``resets`` times."""
    seconds = []
    with JetbotWorld(SimConfig()) as world:
        for _ in range(resets):
            t = time.perf_counter()
            world.reset()
            seconds.append(time.perf_counter() - t)
    a = 1e3 * np.array(seconds)
    return {"resets": resets, "median_ms": round(float(np.median(a)), 3),
            "p10_ms": round(float(np.percentile(a, 10)), 3),
            "p90_ms": round(float(np.percentile(a, 90)), 3)}


# 4.-6., 8. Render variants ---------------------------------------------------------------


@contextlib.contextmanager
def textured_room() -> Iterator[None]:
    """Build the textured room whatever ``[sim]`` says: the default checker is then drawn as
    a texture on room_textured.urdf, what happens when another key needs the textured room."""
    original = looks.textured
    looks.textured = lambda sim: True
    try:
        yield
    finally:
        looks.textured = original


QUAD_OBJ = ("v -1.5 -1.5 0.0\nv 1.5 -1.5 0.0\nv 1.5 1.5 0.0\nv -1.5 1.5 0.0\n"
            "vt 0.0 0.0\nvt 1.0 0.0\nvt 1.0 1.0\nvt 0.0 1.0\nvn 0.0 0.0 1.0\n"
            "f 1/1/1 2/2/1 3/3/1\nf 1/1/1 3/3/1 4/4/1\n")
"""The 3 m floor as one quad (two triangles), texture coordinates as floor_uv.obj's."""


def quad_urdfs(folder: Path) -> dict[str, str]:
    """room.urdf and room_textured.urdf with their floors as one quad, written to
    ``folder`` (with the wall mesh they share)."""
    (folder / "wall.obj").write_text((world_module.ASSETS / "wall.obj").read_text())
    (folder / "floor_quad.obj").write_text(QUAD_OBJ)
    plain = (world_module.ASSETS / looks.PLAIN_ROOM).read_text()
    start = plain.index('    <visual>\n      <geometry><mesh filename="floor_light.obj"')
    end = plain.index("</visual>", plain.index("floor_dark.obj")) + len("</visual>")
    one = ('    <visual>\n      <geometry><mesh filename="floor_quad.obj" scale="1 1 1"/>'
           '</geometry>\n      <material name="floor"><color rgba="0.69 0.667 0.627 1"/>'
           "</material>\n    </visual>")
    texts = {looks.PLAIN_ROOM: plain[:start] + one + plain[end:],
             looks.TEXTURED_ROOM: (world_module.ASSETS / looks.TEXTURED_ROOM).read_text()
             .replace("floor_uv.obj", "floor_quad.obj")}
    for name, text in texts.items():
        (folder / f"quad_{name}").write_text(text)
    return {name: str(folder / f"quad_{name}") for name in texts}


@contextlib.contextmanager
def quad_floor(urdfs: dict[str, str]) -> Iterator[None]:
    """Load ``quad_urdfs``' rooms in place of the package's."""
    original = world_module._asset
    world_module._asset = lambda name: urdfs.get(name) or original(name)
    try:
        yield
    finally:
        world_module._asset = original


@contextlib.contextmanager
def textured_quad_floor(urdfs: dict[str, str]) -> Iterator[None]:
    with textured_room(), quad_floor(urdfs):
        yield


@contextlib.contextmanager
def shadow_map() -> Iterator[None]:
    """``getCameraImage(..., shadow=1)``: TinyRenderer's own shadow map, which the world
    leaves off."""
    original = appearance.light_kwargs
    appearance.light_kwargs = lambda sim: {**original(sim), "shadow": 1}
    try:
        yield
    finally:
        appearance.light_kwargs = original


def egl_render(world: JetbotWorld) -> np.ndarray:
    """The world's pinhole view through PyBullet's EGL renderer (ER_BULLET_HARDWARE_OPENGL)."""
    eye, rotation = world.camera_pose()
    view = p.computeViewMatrix(eye.tolist(), (eye + rotation[:, 0]).tolist(),
                               rotation[:, 2].tolist())
    width, height = world.image_size
    projection = pixel_centred(p.computeProjectionMatrixFOV(
        world.sim.camera_vfov_deg, CAMERA_ASPECT, CAMERA_NEAR, CAMERA_FAR), (width, height))
    _, _, rgba, _, _ = p.getCameraImage(
        width, height, view, projection, renderer=p.ER_BULLET_HARDWARE_OPENGL,
        flags=p.ER_NO_SEGMENTATION_MASK, physicsClientId=world.client,
        **appearance.light_kwargs(world.sim))
    return np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)[:, :, :3].copy()


def load_egl(world: JetbotWorld) -> str:
    """Load the EGL renderer plugin into the world's client; what it printed (or why not)."""
    spec = importlib.util.find_spec("eglRenderer")
    if spec is None or spec.origin is None:
        raise RuntimeError("pybullet's eglRenderer module is not installed")
    with pybullet_chatter_filtered() as printed:
        plugin = p.loadPlugin(spec.origin, "_eglRendererPlugin", physicsClientId=world.client)
    if plugin < 0:
        raise RuntimeError("loadPlugin(eglRenderer) failed: " + " | ".join(printed))
    return " | ".join(line for line in printed if "GL_RENDERER" in line or "EGL" in line)


@dataclass
class Variant:
    world: JetbotWorld
    patch: Callable[[], contextlib.AbstractContextManager[Any]] = contextlib.nullcontext
    render: Callable[[JetbotWorld], np.ndarray] = JetbotWorld.render
    times: list[float] = field(default_factory=list)
    images: list[np.ndarray] = field(default_factory=list)


def variant(size: int, patch: Callable[[], contextlib.AbstractContextManager[Any]]
            = contextlib.nullcontext, **kwargs: Any) -> Variant:
    with patch():
        world = JetbotWorld(PINHOLE, image_size=(size, size))
    return Variant(world, patch, **kwargs)


def time_renders(variants: dict[str, Variant], scenes: list[Scene], rounds: int,
                 repeats: int) -> None:
    """Each variant renders each scene ``repeats`` times a round (after one untimed render,
    kept as its image of the scene), the variants interleaved in rounds."""
    for name in in_rounds(list(variants), rounds):
        v = variants[name]
        for i, scene in enumerate(scenes):
            with v.patch():
                v.world.reset(scene=scene)
            image = v.render(v.world)
            if len(v.images) <= i:
                v.images.append(image)
            for _ in range(repeats):
                t = time.perf_counter()
                v.render(v.world)
                v.times.append(time.perf_counter() - t)


def mad(a: list[np.ndarray], b: list[np.ndarray]) -> float:
    """Mean absolute pixel difference (0..255), over all channels and images."""
    return round(float(np.mean([np.abs(x.astype(np.float32) - y).mean()
                                for x, y in zip(a, b, strict=True)])), 2)


def renders(rounds: int, repeats: int, folder: Path) -> dict[str, Any]:
    """Per size: the meshes (today's room), the checker as a texture, one floor quad, and
    the EGL renderer, over the same scenes; ms a frame and the ratio to the meshes."""
    variants: dict[str, Variant] = {}
    egl: dict[str, Any] = {}
    urdfs = quad_urdfs(folder)
    for size in SIZES:
        variants[f"meshes {size}"] = variant(size)
        variants[f"texture {size}"] = variant(size, textured_room)
        variants[f"quad {size}"] = variant(size, lambda: quad_floor(urdfs))
        variants[f"texture-quad {size}"] = variant(size, lambda: textured_quad_floor(urdfs))
        world = JetbotWorld(PINHOLE, image_size=(size, size))
        try:
            egl["plugin"] = load_egl(world)
            variants[f"egl {size}"] = Variant(world, render=egl_render)
        except RuntimeError as error:
            egl["error"] = str(error)
            world.close()
    time_renders(variants, SCENES, rounds, repeats)
    out: dict[str, Any] = {"scenes": len(SCENES), "renders_per_variant":
                           rounds * len(SCENES) * repeats, "egl": egl, "rows": {}}
    for name, v in variants.items():
        base = variants[f"meshes {name.split()[1]}"]
        out["rows"][name] = {"median_ms": median_ms(v.times),
                             "ratio": round(np.median(v.times) / np.median(base.times), 3),
                             "mad_vs_meshes": mad(v.images, base.images)}
        v.world.close()
    return out


def shadows(rounds: int, repeats: int) -> dict[str, Any]:
    """TinyRenderer's shadow map on a 56x56 frame with a 40 cm box in view: the mean
    absolute grey-level change (luma, 0..255) and the render cost."""
    variants = {"shadow=0": variant(56), "shadow=1": variant(56, shadow_map)}
    time_renders(variants, BOX_SCENES, rounds, repeats)
    luma = np.array([0.299, 0.587, 0.114], np.float32)
    off, on = ([img.astype(np.float32) @ luma for img in v.images] for v in variants.values())
    change = [np.abs(a - b) for a, b in zip(off, on, strict=True)]
    for v in variants.values():
        v.world.close()
    return {"views": len(BOX_SCENES),
            "mean_grey_change": round(float(np.mean([c.mean() for c in change])), 3),
            "per_view_mean_grey_change": [round(float(c.mean()), 3) for c in change],
            "pixels_changed_by_more_than_2_pct": round(
                100 * float(np.mean([(c > 2).mean() for c in change])), 2),
            "darkening_where_changed": round(float(np.mean(
                [(a - b)[c > 2].mean() if (c > 2).any() else 0.0
                 for a, b, c in zip(off, on, change, strict=True)])), 1),
            "median_ms": {n: median_ms(v.times) for n, v in variants.items()},
            "ratio": round(np.median(variants["shadow=1"].times)
                           / np.median(variants["shadow=0"].times), 3)}


# 7. The floor texture's size and its BMP file ---------------------------------------------


def floor_texels(rounds: int) -> dict[str, Any]:
    """Per family, drawing the floor texture (``looks.floor_image``) and a whole textured
    reset (draw, BMP write, loadTexture, the rest of the scene) at 256 and 512 texels."""
    families = list(textures.FLOORS)
    draw: dict[tuple[int, str], list[float]] = {}
    reset: dict[int, list[float]] = {256: [], 512: []}
    original = textures.FLOOR_TEXELS
    with textured_room():
        world = JetbotWorld(PINHOLE, image_size=(56, 56))
        try:
            for texels in in_rounds([256, 512], 2 * rounds):
                textures.FLOOR_TEXELS = texels
                for family in families:
                    sim = SimConfig(lens="pinhole", floor_texture=family)
                    t = time.perf_counter()
                    looks.floor_image(sim)
                    draw.setdefault((texels, family), []).append(time.perf_counter() - t)
                    t = time.perf_counter()
                    world.reset(sim=sim)
                    reset[texels].append(time.perf_counter() - t)
        finally:
            textures.FLOOR_TEXELS = original
            world.close()
    rows = {f: {str(n): median_ms(draw[n, f]) for n in (256, 512)} for f in families}
    total = {n: sum(rows[f][str(n)] for f in families) for n in (256, 512)}
    return {"draw_ms": rows, "draw_ms_all_families": {str(n): round(v, 3) for n, v in
                                                      total.items()},
            "draw_ratio_512_vs_256": round(total[512] / total[256], 2),
            "reset_ms": {str(n): median_ms(s) for n, s in reset.items()},
            "reset_ratio_512_vs_256": round(np.median(reset[512]) / np.median(reset[256]), 2)}


def filesystem(path: str) -> str:
    """The type of the filesystem that holds ``path`` (from /proc/mounts)."""
    best, kind = "", "unknown"
    with contextlib.suppress(OSError):
        for line in Path("/proc/mounts").read_text().splitlines():
            _, mount, fstype, *_ = line.split()
            if (path == mount or path.startswith(mount.rstrip("/") + "/")) and \
                    len(mount) > len(best):
                best, kind = mount, fstype
    return kind


def bmp_writes(rounds: int, writes: int) -> dict[str, Any]:
    """``cv2.imwrite`` of a 256x256 floor BMP then its unlink (what ``looks._load`` does),
    in /dev/shm and in disk-backed directories."""
    image = looks.floor_image(SimConfig(floor_texture="wood"))
    places = [d for d in ("/dev/shm", tempfile.gettempdir(), "/var/tmp") if os.path.isdir(d)]
    folders = {d: tempfile.mkdtemp(prefix="bench_sim_choices-", dir=d) for d in places}
    seconds: dict[str, list[float]] = {d: [] for d in places}
    try:
        for d in in_rounds(places, rounds):
            for i in range(writes):
                path = os.path.join(folders[d], f"floor{i}.bmp")
                t = time.perf_counter()
                cv2.imwrite(path, image)
                os.unlink(path)
                seconds[d].append(time.perf_counter() - t)
    finally:
        for folder in folders.values():
            os.rmdir(folder)
    return {d: {"filesystem": filesystem(d), "median_ms": median_ms(s)}
            for d, s in seconds.items()}


# 9. The camera look ----------------------------------------------------------------------


def camera_look(rounds: int, repeats: int) -> dict[str, float]:
    """``CameraLook.apply`` with every effect on (LOOK), turning at 1 rad/s and driving at
    0.2 m/s, on a rendered frame; ms a frame per size."""
    frames, looks_by_size = {}, {}
    for size in SIZES:
        with JetbotWorld(PINHOLE, image_size=(size, size)) as world:
            frames[size] = world.render()
        looks_by_size[size] = CameraLook(LOOK, (size, size))
    seconds: dict[int, list[float]] = {size: [] for size in SIZES}
    for size in in_rounds(list(SIZES), rounds):
        for _ in range(repeats):
            t = time.perf_counter()
            looks_by_size[size].apply(frames[size], 1.0, 0.2)
            seconds[size].append(time.perf_counter() - t)
    return {str(size): median_ms(s) for size, s in seconds.items()}


# Report ----------------------------------------------------------------------------------


def markdown(r: dict[str, Any]) -> str:
    m = r["machine"]
    lines = [
        "# The simulator's design choices, re-measured", "",
        f"Command: `{r['command']}`  ",
        f"Machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}; 1-min load average "
        f"{m['loadavg_1min_at_start']} at start, {m['loadavg_1min_at_end']} at the end  ",
        f"Date: {r['date']}; versions in sim_choices.json. Timed variants interleaved in "
        f"{r['rounds']} rounds (order rotated each round); medians of wall times; renders "
        "pinhole.", "",
        "## 1. Physics sub-steps (against 240 Hz, the same duties)", "",
        "Max position (mm: the larger of max |dx| and max |dy|, as "
        "`test_the_default_sub_steps_keep_the_trajectories_of_twice_as_many` measures it) / "
        "heading (deg) difference from 240 Hz over the run, after each 30 Hz tick; turned: the "
        "angle turned, and its ratio to 240 Hz's.", "",
        "| duties | " + " | ".join(f"{hz:g} Hz" for hz in RATES) + " |",
        "| --- |" + " --- |" * len(RATES),
    ]
    for name, rows in r["sub_steps"].items():
        cells = [f"{c['max_position_mm']:.1f} mm / {c['max_heading_deg']:.2f} deg"
                 + (f"; turned {c['turned_deg']:.1f} deg (x{c['turn_ratio_vs_240']:.3f})"
                    if name.startswith("sustained") else "") for c in rows.values()]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    curve = next(v for k, v in r["sub_steps"].items() if k.startswith("sustained"))
    straight = next(v for k, v in r["sub_steps"].items() if k.startswith("straight"))
    cost = r["physics_ms_per_tick"]
    lines += [
        "", f"240 Hz turns x{curve['240']['turned_deg'] / curve['960']['turned_deg']:.4f} of "
        f"960 Hz's angle in the curve. The straight run pushed the block "
        f"{straight['240']['block_pushed_mm']:.0f} mm at 240 Hz.", "",
        "Physics of one 30 Hz tick (`step(1/30)`, no render, policy-like duties), median:", "",
        "| physics_hz | " + " | ".join(f"{hz:g}" for hz in RATES) + " |",
        "| --- |" + " --- |" * len(RATES),
        "| ms a tick | " + " | ".join(f"{cost[f'{hz:g}']:.3f}" for hz in RATES) + " |",
        "| ratio to 240 Hz | " + " | ".join(f"{cost[f'{hz:g}'] / cost['240']:.2f}"
                                            for hz in RATES) + " |",
        "", "## 2. reset() of the default world", "",
        f"Median {r['reset']['median_ms']:.2f} ms (p10 {r['reset']['p10_ms']:.2f}, p90 "
        f"{r['reset']['p90_ms']:.2f}) over {r['reset']['resets']} resets (today's [sim] "
        "defaults: the fisheye lens, 224x224).", "",
        "## 3. Render size", "",
        "Not re-measured here: [seam.json](seam.json) has the 56 / 64 / 84 px renders of one "
        "run.", "",
        "## 4.-6. The floor and the renderer, ms a frame", "",
        f"The same {r['renders']['scenes']} views (the seed scene and five across the room), "
        f"{r['renders']['renders_per_variant']} renders a variant. meshes: room.urdf's "
        "checker as two plain-coloured meshes (today's default room); texture: the same "
        "checker as a 256-texel texture on room_textured.urdf's 24x24-quad floor (the room "
        "forced textured, nothing else changed); quad: room.urdf with the floor as one plain "
        "quad (two triangles); texture-quad: the textured room with its floor as one quad; "
        "egl: the meshes through PyBullet's EGL renderer (`ER_BULLET_HARDWARE_OPENGL`), which "
        "draws one colour per link (the room's checker and walls come out one grey; a loaded "
        "EGL plugin also takes over that client's `ER_TINY_RENDERER` calls). Pixel "
        "difference: mean absolute (0..255) from the meshes' image of the same view.", "",
        "| variant | median | ratio to the meshes | pixel difference |",
        "| --- | --- | --- | --- |",
    ]
    for name, row in r["renders"]["rows"].items():
        lines.append(f"| {name}x{name.split()[1]} | {row['median_ms']:.3f} ms | "
                     f"x{row['ratio']:.2f} | {row['mad_vs_meshes']} |")
    rows, egl = r["renders"]["rows"], r["renders"]["egl"]
    lines += ["", "One textured quad against the textured 24x24-quad floor: " + ", ".join(
        f"x{rows[f'texture-quad {n}']['median_ms'] / rows[f'texture {n}']['median_ms']:.2f} at "
        f"{n}x{n}" for n in SIZES) + ".", "",
        f"EGL: {egl.get('error') or egl.get('plugin') or 'loaded'}.", ""]
    t, s = r["floor_texels"], r["shadows"]
    lines += [
        "## 7. The floor texture: 256 against 512 texels; where its BMP is written", "",
        "Drawing the texture (`looks.floor_image`), median ms per family; a whole reset with "
        "the family's textured floor (draw, BMP write, `loadTexture`, the rest of the scene):",
        "", "| family | 256 | 512 | ratio |", "| --- | --- | --- | --- |",
    ]
    for family, row in t["draw_ms"].items():
        lines.append(f"| {family} | {row['256']:.2f} ms | {row['512']:.2f} ms | "
                     f"x{row['512'] / row['256']:.1f} |")
    lines += [
        f"| all seven, summed | {t['draw_ms_all_families']['256']:.1f} ms | "
        f"{t['draw_ms_all_families']['512']:.1f} ms | x{t['draw_ratio_512_vs_256']} |",
        f"| reset, all families | {t['reset_ms']['256']:.2f} ms | {t['reset_ms']['512']:.2f} "
        f"ms | x{t['reset_ratio_512_vs_256']} |", "",
        "A 256x256 BMP written with `cv2.imwrite` and unlinked, median:", "",
        "| directory | filesystem | ms a write |", "| --- | --- | --- |",
        *(f"| {d} | {w['filesystem']} | {w['median_ms']:.3f} |"
          for d, w in r["bmp_writes"].items()),
        "", "## 8. TinyRenderer's shadow map (56x56, a 40 cm box in view)", "",
        f"Over {s['views']} views of the box from 1 m: `shadow=1` against `shadow=0` changes "
        f"the frame by {s['mean_grey_change']} grey levels on average (luma, 0..255; per view "
        f"{', '.join(map(str, s['per_view_mean_grey_change']))}); "
        f"{s['pixels_changed_by_more_than_2_pct']} % of the pixels change by more than 2, "
        f"darkened by {s['darkening_where_changed']} there. Render: "
        f"{s['median_ms']['shadow=0']:.3f} ms without, {s['median_ms']['shadow=1']:.3f} ms with "
        f"(x{s['ratio']:.2f}).", "",
        "## 9. The camera look alone", "",
        "`CameraLook.apply` with exposure 1.3, white balance (1.1, 1, 0.9), gain noise 0.03, "
        "vignetting 0.5 and 20 ms of motion blur, turning at 1 rad/s at 0.2 m/s: "
        + ", ".join(f"{ms:.3f} ms a {size}x{size} frame" for size, ms in r["camera_look"].items())
        + ".",
    ]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args()
    result: dict[str, Any] = {
        **run_record(), "machine": machine(), "rounds": args.rounds}
    steps: list[tuple[str, Callable[[], Any]]] = [
        ("sub_steps", sub_steps),
        ("physics_ms_per_tick", lambda: physics_cost(args.rounds, 90)),
        ("reset", lambda: reset_cost(40 * args.rounds)),
        ("camera_look", lambda: camera_look(args.rounds, 400)),
        ("floor_texels", lambda: floor_texels(args.rounds)),
        ("bmp_writes", lambda: bmp_writes(args.rounds, 40)),
        ("shadows", lambda: shadows(args.rounds, 10)),
    ]
    with tempfile.TemporaryDirectory(prefix="bench_sim_choices-") as folder:
        steps.append(("renders", lambda: renders(args.rounds, 8, Path(folder))))
        for key, run in steps:
            t = time.perf_counter()
            result[key] = run()
            print(f"{key}: {time.perf_counter() - t:.0f} s", flush=True)
    result["machine"]["loadavg_1min_at_end"] = round(os.getloadavg()[0], 2)
    write_results(args.out, "sim_choices", result, markdown(result))


if __name__ == "__main__":
    main()
