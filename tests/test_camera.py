"""Windshield cameras: the pinhole render follows the geometry (curves, distance, camera offsets, occlusion),
noise is seeded and has the configured size, and the wrapper passes Gymnasium's checker."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from highway_env.vehicle.kinematics import Vehicle

import av_gym  # noqa: F401  (registers the envs)
from av_gym.sensors.camera import (ASPHALT, CAMERA_NAMES, MARKING, CameraNoise, Cameras, CameraSpec, Weather,
                                   camera_rig, render_view, render_views, scene_of)

LANE_ID, TURN_ID = "av_gym/LaneKeepingLap-v0", "av_gym/UnprotectedLeftTurn-v0"
PIXEL_ONLY = CameraNoise(pixel_std=6.0, brightness=0.0, contrast=0.0, camera_gain=0.0)


def lap_env(track: str = "A", start_s: float = 0.0) -> gym.Env:
    """A lap env reset with the car exactly on the centreline at ``start_s`` (m), heading along the lane."""
    env = gym.make(LANE_ID, config={"track": track, "start_s": start_s, "initial_lateral_std": 0.0,
                                    "initial_heading_std": 0.0})
    env.reset(seed=0)
    return env


def road_mask(img: np.ndarray) -> np.ndarray:
    """(H, W) bool: asphalt or lane-marking pixels of a clean render."""
    px = img.astype(int)
    return (np.abs(px - ASPHALT).max(-1) <= 12) | (np.abs(px - MARKING).max(-1) <= 30)


def road_centre_column(img: np.ndarray, rows: slice) -> float:
    """Mean column (px) of road pixels in ``rows``, averaged over the rows that show road."""
    mask = road_mask(img)[rows]
    cols = [np.flatnonzero(r).mean() for r in mask if r.any()]
    assert cols, "no road pixels in these rows"
    return float(np.mean(cols))


def add_car(env: gym.Env, ahead: float, lateral: float = 0.0) -> Vehicle:
    """Park a car ``ahead`` m in front of the ego (and ``lateral`` m to its right), facing the same way."""
    u = env.unwrapped
    psi = u.vehicle.heading
    f, r = np.array([np.cos(psi), np.sin(psi)]), np.array([-np.sin(psi), np.cos(psi)])
    car = Vehicle(u.road, u.vehicle.position + ahead * f + lateral * r, heading=psi, speed=0.0)
    u.road.vehicles.append(car)
    return car


# ------------------------------------------------------------------------------------------------ geometry
@pytest.mark.parametrize("track, start_s, direction", [("A", 110.0, -1), ("B", 90.0, +1), ("A", 0.0, 0)])
def test_road_bends_towards_the_curve(track, start_s, direction):
    # Layout A: 120 m straight, then a 25 m LEFT hairpin; layout B: 100 m straight, then a 22 m RIGHT hairpin.
    # 10 m before the curve, the road near the horizon must lie left (A) / right (B) of the road at the bottom.
    spec = CameraSpec()
    img = render_view(lap_env(track, start_s), spec)
    h = int(np.ceil(spec.horizon_row))
    far = road_centre_column(img, slice(h + 4, h + 16))
    near = road_centre_column(img, slice(spec.height - 16, spec.height))
    assert near == pytest.approx((spec.width - 1) / 2, abs=1.0)  # on the centreline, looking along the lane
    if direction == 0:
        assert far == pytest.approx(near, abs=1.0)
    else:
        assert direction * (far - near) > 5.0, (far, near)


def test_near_car_is_larger_than_far_car_and_red():
    env = lap_env("A", 0.0)  # 120 m straight ahead
    spec = CameraSpec()
    empty = render_view(env, spec)
    sizes = {}
    for ahead in (10.0, 40.0):
        car = add_car(env, ahead)
        img = render_view(env, spec)
        env.unwrapped.road.vehicles.remove(car)
        changed = np.any(img != empty, axis=-1)
        rows, cols = np.flatnonzero(changed.any(1)), np.flatnonzero(changed.any(0))
        sizes[ahead] = (changed.sum(), len(rows), len(cols))
        red = (img[..., 0].astype(int) > img[..., 1].astype(int) + 60) & changed
        assert red.sum() > 0.3 * changed.sum(), "the car is drawn in the vehicle colour"
    near, far = sizes[10.0], sizes[40.0]
    assert far[0] > 0
    assert near[0] > 4 * far[0] and near[1] > far[1] and near[2] > far[2], sizes


def test_near_car_hides_a_car_behind_it():
    # Painter's order: the far box is drawn first and must be fully covered by the near one (camera 1.4 m high,
    # boxes 1.5 m tall and 2 m wide, in line).
    env = lap_env("A", 0.0)
    add_car(env, 10.0)
    before = render_view(env)
    add_car(env, 30.0)
    np.testing.assert_array_equal(render_view(env), before)


def test_side_cameras_see_the_road_shifted_the_right_way():
    env = lap_env("A", 0.0)
    views = render_views(env, camera_rig())
    for a, b in (("left", "centre"), ("centre", "right"), ("left", "right")):
        assert np.any(views[a] != views[b])
    bottom = slice(40, 66)
    cols = {name: road_centre_column(views[name], bottom) for name in CAMERA_NAMES}
    # The left camera sits 0.6 m left of the centreline, so the road lies to its right (larger columns).
    assert cols["left"] > cols["centre"] + 3 > cols["right"] + 6, cols


def test_displaced_pose_equals_side_camera():
    # render_view(pose=...) renders what a camera would see from another ego pose: the centre camera moved
    # 0.6 m left is the left camera. The original renderer made them bit-identical; the texture renderer turns
    # poles and trees towards the rig's centre (shared by its three cameras), so a few pole edges move by a pixel.
    env = lap_env("A", 0.0)
    x, y, psi = *env.unwrapped.vehicle.position, env.unwrapped.vehicle.heading
    pose = np.array([x + 0.6 * np.sin(psi), y - 0.6 * np.cos(psi), psi])
    left = render_views(env, camera_rig(), ground="raster")["left"]
    np.testing.assert_array_equal(render_view(env, CameraSpec(), pose=pose, ground="raster"), left)
    left = render_views(env, camera_rig())["left"]
    diff = np.abs(render_view(env, CameraSpec(), pose=pose).astype(int) - left).max(-1)
    assert (diff > 0).mean() < 0.002 and diff.mean() < 0.1, ((diff > 0).mean(), diff.mean())


def test_renders_from_awkward_poses_without_folding():
    # Poses off the road, facing scenery or straddling other cars exercise near-plane clipping; every frame must
    # be a valid image, and a building straight ahead at 1.5 m must fill most of the view.
    env = gym.make(TURN_ID)
    env.reset(seed=1)
    for _ in range(10):
        env.step(1)
    u = env.unwrapped
    rng = np.random.default_rng(0)
    for _ in range(40):
        pose = np.array([rng.uniform(-40, 40), rng.uniform(-40, 40), rng.uniform(-np.pi, np.pi)])
        img = render_view(env, pose=pose)
        assert img.shape == (66, 200, 3) and img.dtype == np.uint8
    others = [v for v in u.road.vehicles if v is not u.vehicle]
    for v in others[:3]:  # camera inside another car
        render_view(env, pose=np.array([*v.position, v.heading]))
    scene = scene_of(env)
    big = np.flatnonzero(scene.walls[:, 2, 2] > 5.0)[0]  # a piece of building front
    a, b = scene.walls[big, 0, :2], scene.walls[big, 1, :2]
    mid, along = (a + b) / 2, (b - a) / np.linalg.norm(b - a)
    normal = np.array([-along[1], along[0]])
    for sign in (1.0, -1.0):
        eye = mid + sign * 2.0 * normal  # camera 0.5 m ahead of the pose → 1.5 m from the wall
        img = render_view(env, pose=np.array([*eye, np.arctan2(-sign * normal[1], -sign * normal[0])]))
        assert np.all(img == img[0, 0], axis=-1).mean() > 0.5, "the wall fills the view"


# ------------------------------------------------------------------------------------------------ wrapper and noise
def test_observation_space_and_other_keys_untouched():
    env = Cameras(gym.make(LANE_ID), height=40, width=120, hfov_deg=80.0)
    obs, info = env.reset(seed=3)
    assert set(obs) == {"state", "cameras"} and env.observation_space.contains(obs)
    assert set(obs["cameras"]) == set(CAMERA_NAMES)
    assert obs["cameras"]["centre"].shape == (40, 120, 3)
    obs, *_ = env.step(np.zeros(1, np.float32))
    assert env.observation_space.contains(obs)


def test_same_seed_same_images_different_seed_different_noise():
    env = Cameras(gym.make(LANE_ID))
    a, _ = env.reset(seed=7)
    b, _ = env.reset(seed=7)
    c, _ = env.reset(seed=8)
    for name in CAMERA_NAMES:
        np.testing.assert_array_equal(a["cameras"][name], b["cameras"][name])
        assert np.any(a["cameras"][name] != c["cameras"][name])
    # Noise comes only from the sensor's generator: same scene, other generator → other noise.
    env.reset(seed=7)
    env.rng = np.random.default_rng(123)
    env.on_reset()
    d = env.measure()
    assert all(np.any(d[n] != a["cameras"][n]) for n in CAMERA_NAMES)


def test_noise_off_is_the_clean_render_for_any_generator():
    env = Cameras(gym.make(LANE_ID), noise=False)
    env.reset(seed=7)
    clean = render_views(env, env.specs)
    for seed in (1, 2):
        env.rng = np.random.default_rng(seed)
        env.on_reset()
        got = env.measure()
        for name in CAMERA_NAMES:
            np.testing.assert_array_equal(got[name], clean[name])


@pytest.mark.parametrize("env_id", [LANE_ID, TURN_ID])
def test_pixel_noise_has_the_configured_std(env_id):
    env = Cameras(gym.make(env_id), noise=PIXEL_ONLY)
    obs, _ = env.reset(seed=4)
    clean = render_views(env, env.specs)
    for name in CAMERA_NAMES:
        diff = obs["cameras"][name].astype(float) - clean[name]
        assert diff.std() == pytest.approx(PIXEL_ONLY.pixel_std, rel=0.15)
        assert abs(diff.mean()) < 0.3


def test_exposure_is_per_episode_and_per_camera():
    noise = CameraNoise(pixel_std=0.0, brightness=20.0, contrast=0.0, camera_gain=0.1)
    env = Cameras(gym.make(LANE_ID), noise=noise)
    offsets = []
    for _ in range(2):
        obs, *_ = env.step(np.zeros(1, np.float32)) if offsets else env.reset(seed=5)
        clean = render_views(env, env.specs)
        offsets.append({n: obs["cameras"][n].astype(float).mean() - clean[n].mean() for n in CAMERA_NAMES})
    for n in CAMERA_NAMES:
        assert offsets[0][n] == pytest.approx(offsets[1][n], abs=1.0)  # same exposure all episode
    assert len({round(v, 1) for v in offsets[0].values()}) == 3  # each camera its own gain


def test_frame_hold_at_a_lower_rate():
    env = Cameras(gym.make(LANE_ID), rate_hz=5.0)  # policy at 10 Hz: a new frame every other step
    frames = [env.reset(seed=2)[0]["cameras"]["centre"]]
    for _ in range(4):
        frames.append(env.step(np.zeros(1, np.float32))[0]["cameras"]["centre"])
    np.testing.assert_array_equal(frames[0], frames[1])
    np.testing.assert_array_equal(frames[2], frames[3])
    assert np.any(frames[1] != frames[2]) and np.any(frames[3] != frames[4])


def test_fog_fades_far_things_more_and_night_is_darker():
    env = lap_env("A", 0.0)
    spec = CameraSpec()
    clear = render_view(env, spec).astype(float)
    foggy = render_view(env, spec, weather=Weather(fog_visibility=80.0)).astype(float)
    road = road_mask(clear.astype(np.uint8))
    h = int(np.ceil(spec.horizon_row))
    loss = np.abs(foggy - clear).mean(-1)
    far, near = loss[h + 2:h + 8][road[h + 2:h + 8]].mean(), loss[-8:][road[-8:]].mean()
    assert far > near + 20  # road at ~50 m shifts most of the way to the airlight, road at ~4 m barely
    night = render_view(env, spec, weather=Weather(night=True)).astype(float)
    assert night.mean() < 0.5 * clear.mean()
    # headlights: the road just ahead is lit more than the road near the horizon
    assert night[-8:][road[-8:]].mean() > 1.5 * night[h + 2:h + 8][road[h + 2:h + 8]].mean()


def test_a_subset_of_views_renders_the_same_images():
    full = Cameras(gym.make(LANE_ID), noise=False)
    centre = Cameras(gym.make(LANE_ID), noise=False, views=["centre"])
    a, _ = full.reset(seed=4)
    b, _ = centre.reset(seed=4)
    assert set(b["cameras"]) == {"centre"} and centre.observation_space.contains(b)
    np.testing.assert_array_equal(a["cameras"]["centre"], b["cameras"]["centre"])
    with pytest.raises(ValueError, match="views"):
        Cameras(gym.make(LANE_ID), views=["rear"])


def test_bad_arguments_are_rejected():
    with pytest.raises(ValueError):
        CameraSpec(hfov_deg=0.0)
    with pytest.raises(ValueError):
        CameraNoise(pixel_std=-1.0)
    with pytest.raises(ValueError):
        Cameras(gym.make(LANE_ID), rate_hz=0.0)


@pytest.mark.parametrize("env_id, config", [(LANE_ID, {}), (TURN_ID, {}), (TURN_ID, {"mode": "ccftap"})])
def test_check_env_passes(env_id, config):
    check_env(Cameras(gym.make(env_id, config=config)), skip_render_check=True)


# ------------------------------------------------------------------------------------------------ texture renderer
def _drive(env_id: str, steps: int, seed: int):
    """Yield the env after each of ``steps`` steps of a plain drive (lap: PID-free straight steering is enough to
    cover straights and the start of curves; turn: IDLE through the intersection with traffic)."""
    env = gym.make(env_id)
    env.reset(seed=seed)
    for _ in range(steps):
        _, _, term, trunc, _ = env.step(np.zeros(1) if env_id == LANE_ID else 1)
        if term or trunc:
            env.reset(seed=seed + 1)
        yield env


@pytest.mark.parametrize("env_id, weather", [(LANE_ID, Weather()), (TURN_ID, Weather()),
                                             (LANE_ID, Weather(night=True)), (TURN_ID, Weather(fog_visibility=80.0))])
def test_texture_renderer_draws_the_same_picture_as_the_raster_renderer(env_id, weather):
    # The ground sampled from the top-down texture (one bilinear sample per output pixel) against every road
    # polygon projected and area-averaged: equal up to edge pixels, on the same poses.
    diffs = []
    for env in _drive(env_id, 40, seed=3):
        new = render_views(env, camera_rig(), weather=weather)
        old = render_views(env, camera_rig(), weather=weather, ground="raster")
        diffs += [np.abs(new[k].astype(int) - old[k]).max(-1) for k in CAMERA_NAMES]
    d = np.stack(diffs)
    assert d.mean() < 2.5 and (d > 30).mean() < 0.04, (d.mean(), (d > 30).mean())


def test_the_closeness_bound_sees_a_small_pose_error():
    # The bounds above are tight enough to notice a texture off by 0.3 m (a wrong origin or scale would be worse).
    env = lap_env("A", 110.0)
    x, y, psi = *env.unwrapped.vehicle.position, env.unwrapped.vehicle.heading
    old = render_view(env, ground="raster")
    new = render_view(env, pose=np.array([x - 0.3 * np.sin(psi), y + 0.3 * np.cos(psi), psi]))
    d = np.abs(new.astype(int) - old).max(-1)
    assert (d > 30).mean() > 0.04, (d > 30).mean()


def test_texture_covers_the_road_and_its_markings():
    env = lap_env("A", 0.0)
    from av_gym.sensors.camera import ground_texture

    tex = ground_texture(scene_of(env))
    lane = env.unwrapped.road.network.lanes_list()[0]

    def texel(s: float, lat: float) -> int:
        x, y = lane.position(s, lat)
        return int(tex.texels[int(round((y - tex.y0) / tex.res)), int(round((x - tex.x0) / tex.res))])

    w = lane.width_at(0.0)
    assert texel(30.0, 0.0) == 128  # asphalt on the centreline
    assert texel(30.0, w / 2) == 255 or texel(30.0, -w / 2) == 255  # an edge line
    assert texel(30.0, w / 2 + 0.5) == 0 and texel(30.0, -w / 2 - 0.5) == 0  # grass


# ------------------------------------------------------------------------------------------------ fast paths
@pytest.mark.parametrize("env_id", [LANE_ID, TURN_ID])
def test_painting_only_the_band_the_quads_cover_gives_the_same_pixels(env_id):
    # The band shortcut must be exact: nearest enlargement and 2x2 area averaging work block by block.
    import cv2

    from av_gym.sensors.camera import ground_texture
    from av_gym.sensors.camera_render import _draw_rig_ground, _render_rig, others_state

    drawn = 0
    for env in _drive(env_id, 25, seed=5):
        scene = scene_of(env)
        local = scene.near(env.unwrapped.vehicle.position, 200.0, ground=False)
        pose = np.array([*env.unwrapped.vehicle.position, env.unwrapped.vehicle.heading])
        args = (local, others_state(env), pose, camera_rig(), Weather(), ground_texture(scene))
        band, whole = _render_rig(*args), _render_rig(*args, whole_image=True)
        ground = _draw_rig_ground(pose, list(camera_rig().values()), ground_texture(scene))
        for k, g in zip(CAMERA_NAMES, ground):
            np.testing.assert_array_equal(band[k], whole[k])
            drawn += int(np.any(band[k] != cv2.cvtColor(g, cv2.COLOR_RGBA2RGB)))
    assert drawn > 0  # vertical things were drawn over the ground


def test_a_sideways_camera_is_culled_and_drawn_like_the_raster_renderer():
    # Cameras with yaw take the general (not the windshield-rig) path, whose culling must not drop what they see.
    env = next(iter(_drive(TURN_ID, 30, seed=2)))
    rig = {"side": CameraSpec(yaw_deg=60.0), "back": CameraSpec(yaw_deg=180.0, lateral_offset=0.3)}
    new, old = render_views(env, rig), render_views(env, rig, ground="raster")
    for k in rig:
        d = np.abs(new[k].astype(int) - old[k]).max(-1)
        assert d.mean() < 2.5 and (d > 30).mean() < 0.04, (k, d.mean(), (d > 30).mean())


def test_pixel_noise_from_the_bank_is_independent_per_pixel_and_frame():
    # Each frame takes a window of a fixed, seeded bank at an offset drawn from the wrapper's generator: within a
    # frame N(0, sigma) per pixel; across frames a pixel's noise is uncorrelated (the same value only if two
    # offsets coincide); the residuals are the bank's values (exposure off, so frame = clean + sigma * bank).
    from av_gym.sensors.camera import NOISE_BANK_SIZE, _noise_bank

    noise = CameraNoise(pixel_std=8.0, brightness=0.0, contrast=0.0, camera_gain=0.0)
    env = Cameras(gym.make(LANE_ID), noise=noise, rate_hz=None)
    env.reset(seed=11)
    res = []
    for _ in range(6):
        obs, *_ = env.step(np.zeros(1, np.float32))
        clean = render_views(env, env.specs)
        res.append(np.stack([obs["cameras"][n].astype(float) - clean[n] for n in CAMERA_NAMES]))
    r = np.stack(res)  # (frames, cameras, H, W, 3)
    inner = (r > -200) & (r < 200)  # residual with no clipping at 0/255 (clean frames stay within ~[20, 230])
    assert inner.all()
    assert r.std() == pytest.approx(8.0, rel=0.05) and abs(r.mean()) < 0.2
    flat = r.reshape(len(r), -1)
    for a, b in zip(flat[:-1], flat[1:]):  # same pixel, consecutive frames
        assert abs(np.corrcoef(a, b)[0, 1]) < 0.03
    cams = r[0].reshape(3, -1)  # the three cameras of one frame: disjoint windows
    assert abs(np.corrcoef(cams[0], cams[1])[0, 1]) < 0.03
    # the residuals are the bank's window at the offset the wrapper's generator draws
    bank = _noise_bank()
    assert len(bank) == NOISE_BANK_SIZE
    g = np.random.default_rng()
    g.bit_generator.state = env.rng.bit_generator.state
    obs, *_ = env.step(np.zeros(1, np.float32))
    clean = render_views(env, env.specs)
    start = int(g.integers(0, NOISE_BANK_SIZE - 3 * 66 * 200 * 3 + 1))
    for j, n in enumerate(CAMERA_NAMES):
        window = bank[start + j * 66 * 200 * 3:start + (j + 1) * 66 * 200 * 3].reshape(66, 200, 3)
        np.testing.assert_array_equal(obs["cameras"][n].astype(int) - clean[n], np.rint(8.0 * window))
