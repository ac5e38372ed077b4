"""The AEB shield's conflict model (av_gym/shields/conflicts.py, target_model conflict)."""

from __future__ import annotations

import numpy as np
import pytest

from agents import AlwaysProceed
from av_gym.shields.conflicts import ConflictModel, path_turn
from av_gym.sensors.turn_signal import TurnSignalsParams
from av_gym.estimation.driver_intent import DriverIntent, reading_likelihood

CHANNEL = TurnSignalsParams(no_signal_rate=0.25, wrong_rate=0.05, miss_rate=0.1)
from conftest import conf

LEFT_FROM_EAST = (("o3", "ir3", 0), ("ir3", "il0", 0), ("il0", "o0", 0))


def test_path_turn_is_the_indicator_a_driver_on_that_path_shows():
    assert path_turn(LEFT_FROM_EAST) == 1.0
    assert path_turn((("o3", "ir3", 0), ("ir3", "il2", 0), ("il2", "o2", 0))) == -1.0
    assert path_turn((("o3", "ir3", 0), ("ir3", "il1", 0), ("il1", "o1", 0))) == 0.0
    assert path_turn((("ir0", "il1", 0), ("il1", "o1", 0))) == 1.0  # already in the box
    assert path_turn((("il1", "o1", 0),)) == 0.0  # on an exit: unknown


def _read(readings, floor=0.02):
    """Turn weights (right, straight, left) of one driver after ``readings``, channel defaults."""
    belief = DriverIntent(CHANNEL, floor=floor)
    for r in readings:
        belief.update(["driver"], [r])
    return belief.turn_weights(["driver"])[0]


def test_one_reading_weighs_the_turns_as_the_indicator_channel_says():
    shown = 0.75 * 0.9  # indicates (75 %) and the reading does not miss it (90 %)
    for reading, expected in ((1.0, [shown * 0.05, 0.0, shown * 0.95]), (0.0, [1 - shown, 1.0, 1 - shown])):
        np.testing.assert_allclose(_read([reading], floor=1e-9), np.array(expected) / max(expected), rtol=1e-6,
                                   atol=1e-8)
    assert reading_likelihood(1.0, 0.1, floor=0.02)[1].tolist() == [0.02] * 3  # straight never indicates: floor
    assert np.isnan(DriverIntent(CHANNEL).turn_weights(["never read"])).all()


def test_readings_accumulate_the_per_reading_misses_average_out_the_per_driver_ones_do_not():
    w = _read([-1.0, 0.0, -1.0, -1.0])  # a right indicator, missed once
    p = w / w.sum()
    assert p[0] > 0.9 and p[1] < 0.05  # one miss among three readings does not bring straight back
    w = _read([0.0] * 20)
    # never indicating: a turn stays possible at P(never) = 25 % against straight's 100 %
    np.testing.assert_allclose(w / w.sum(), [0.25 / 1.5, 1 / 1.5, 0.25 / 1.5], rtol=1e-3)


def test_the_belief_is_filterpy_s_discrete_bayes_update_applied_reading_by_reading():
    from filterpy.discrete_bayes import update

    rng = np.random.default_rng(0)
    for _ in range(20):
        readings = rng.choice([-1.0, 0.0, 1.0], size=int(rng.integers(1, 40)), p=[0.2, 0.6, 0.2])
        belief = DriverIntent(CHANNEL)
        post = belief.prior.copy()
        for r in readings:
            belief.update(["driver"], [r])
            post = update(reading_likelihood(r, 0.1, 0.02).ravel(), post)
        np.testing.assert_allclose(belief.posterior([belief.counts["driver"]])[0], post, rtol=1e-9, atol=1e-300)


def test_many_drivers_are_updated_as_each_alone():
    together = DriverIntent(CHANNEL)
    readings = {"a": [1.0, 1.0, 0.0], "b": [0.0, 0.0, 0.0], "c": [-1.0, 1.0, -1.0]}
    for k in range(3):
        together.update(list(readings), np.array([r[k] for r in readings.values()]))
    for i, (key, seq) in enumerate(readings.items()):
        np.testing.assert_allclose(together.turn_weights([key])[0], _read(seq), rtol=1e-12)


@pytest.fixture
def network(make, turn_cfg):
    env = make(turn_cfg, None, None)
    env.reset(seed=0)
    return env.unwrapped.road.network


def _on_approach(network, speed=8.0):
    lane = network.get_lane(("o3", "ir3", 0))
    s = lane.length - 20.0
    x, y = lane.position(s, 0.0)
    h = lane.heading_at(s)
    return np.array([[x, y, speed * np.cos(h), speed * np.sin(h), h, 5.0, 2.0]])


def test_every_continuation_is_a_hypothesis_and_a_turn_signal_prunes_straight(network):
    model = ConflictModel(network, min_p=0.1)
    t = 0.1 * np.arange(1, 41)
    t.flags.writeable = False  # as the shield hands it (long_times): the kernels' own specialization
    others = _on_approach(network)
    lanes = [("o3", "ir3", 0)]
    xy, h, owner, is_map, p = model.predict(others, lanes, np.zeros((1, 2)), t)
    assert xy.shape == (40, 3, 2) and list(owner) == [0, 0, 0] and is_map.all()
    assert p == pytest.approx([1 / 3] * 3)
    # the three paths end in three different places after 4 s
    ends = xy[-1]
    assert min(np.hypot(*(ends[i] - ends[j])) for i in range(3) for j in range(i + 1, 3)) > 5.0

    full = xy
    left = [turn for _, turn in model.hypotheses(lanes[0])].index(1.0)
    xy, h, owner, is_map, p = model.predict(others, lanes, np.zeros((1, 2)), t, _read([1.0])[None])  # one reading: left
    assert len(owner) == 1 and p[0] > 0.85  # left only: straight (floor) and right (wrong side) below min_p
    np.testing.assert_allclose(xy[:, 0], full[:, left])


def test_a_reading_that_weighs_every_continuation_zero_leaves_them_uniform(network):
    """Indicator weights that are 0 for every turn a lane continues to (a reading that rules out all of them, as a
    caller's hard 0/1 weights can; DriverIntent floors its own at 0.02) say nothing about which continuation: the
    weights are uniform, as without a reading, not 0/0 (a NaN probability and a RuntimeWarning before), in the
    Python reference (ConflictModel._select) and the kernel alike: a car on the approach read [0, 0, 0], and one in
    the box on its left turn read right-or-straight only."""
    import warnings

    from av_gym.shields import conflicts

    t = 0.1 * np.arange(1, 21)
    t.flags.writeable = False  # as the shield hands it (long_times): the kernels' own specialization
    in_box = network.get_lane(("ir3", "il0", 0))
    x, y = in_box.position(2.0, 0.0)
    h = in_box.heading_at(2.0)
    others = np.vstack([_on_approach(network), [[x, y, 6.0 * np.cos(h), 6.0 * np.sin(h), h, 5.0, 2.0]]])
    lanes = [("o3", "ir3", 0), ("ir3", "il0", 0)]
    intent = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    model = ConflictModel(network, min_p=0.1)
    assert [turn for _, turn in model.hypotheses(lanes[1])] == [1.0]  # the box's left turn: left only
    outs = []
    for kernel in (True, False):
        conflicts.CONFLICT_KERNEL = kernel
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                outs.append(model.predict(others, lanes, np.zeros((2, 2)), t, intent))
        finally:
            conflicts.CONFLICT_KERNEL = True
    for got, want in zip(*outs):
        np.testing.assert_array_equal(got, want, strict=True)
    _, _, owner, is_map, p = outs[0]
    assert owner.tolist() == [0, 0, 0, 1] and is_map.all()
    assert p.tolist() == [1 / 3, 1 / 3, 1 / 3, 1.0]


def test_standing_or_off_the_map_objects_get_constant_velocity(network):
    model = ConflictModel(network)
    t = 0.1 * np.arange(1, 11)
    t.flags.writeable = False  # as the shield hands it (long_times): the kernels' own specialization
    standing = _on_approach(network, speed=0.0)
    off_map = _on_approach(network)
    off_map[0, 0:2] += np.array([0.0, 6.0])  # 6 m to the side of its lane
    for obj, lane in ((standing, ("o3", "ir3", 0)), (off_map, ("o3", "ir3", 0)), (_on_approach(network), None)):
        xy, h, owner, is_map, p = model.predict(obj, [lane], np.zeros((1, 2)), t)
        assert len(owner) == 1 and not is_map[0]
        np.testing.assert_allclose(xy[-1, 0], obj[0, 0:2] + obj[0, 2:4] * t[-1])


def _episode(make, turn_cfg, seed, **shield):
    cfg = conf("shield", "aeb")
    cfg.update(shield)
    env = make(turn_cfg, None, cfg)
    policy = AlwaysProceed(env.unwrapped.cruise_action())
    obs, _ = env.reset(seed=seed)
    done = False
    while not done:
        obs, _, term, trunc, info = env.step(policy.act(obs))
        done = term or trunc
    return info["episode_metrics"]


def test_a_car_turning_across_from_the_right_is_braked_for(make, turn_cfg):
    # seed 1025: a car from the east turns left across the ego's path into the south exit; constant velocity
    # never predicts the conflict (no intervention, collision), the conflict model does
    cv = _episode(make, turn_cfg, 1025, target_model="cv")
    assert cv["collision"] == 1.0 and cv["interventions"] == 0
    conflict = _episode(make, turn_cfg, 1025, target_model="conflict")
    assert conflict["collision"] == 0.0 and conflict["interventions"] >= 1


def test_an_indicating_driver_is_not_braked_for_on_a_path_its_indicator_rules_out(make, turn_cfg):
    # seed 1015: without intent the shield stops the ego at the line for a path hypothesis of a car that merges
    # later (the counterfactual replay: no collision without the brake) and the ego arrives after 18.5 s; reading
    # that driver's indicator (a channel without noise, so the test does not hang on the channel's draws) rules
    # the path out and the ego goes
    blind = _episode(make, turn_cfg, 1015, signals=False)
    assert blind["interventions"] >= 1 and blind["collision"] == 0.0
    read = _episode(make, turn_cfg, 1015, signals=True,
                    signal_channel={"no_signal_rate": 0.0, "wrong_rate": 0.0, "miss_rate": 0.0})
    assert read["interventions"] == 0 and read["collision"] == 0.0 and read["success"] == 1.0
    assert read["duration_s"] < blind["duration_s"] - 5.0


@pytest.mark.parametrize("mode", ["ground_truth", "perceived"])
def test_each_object_reads_the_indicator_of_the_car_it_is(make, turn_cfg, mode):
    # a channel without noise: every object read within 60 m must weigh its own car's intended turn highest, in
    # perceived mode a track too (its reading belongs to the vehicle within 2 m of it); once a car is on its exit
    # road its indicator is off and it has one path left, so only approach and box lanes are checked
    from av_gym.sensors.turn_signal import intended_signal
    from av_gym.shields.aeb import find_shield

    cfg = conf("shield", "aeb")
    cfg.update(mode=mode, signal_channel={"no_signal_rate": 0.0, "wrong_rate": 0.0, "miss_rate": 0.0})
    env = make(turn_cfg, None, cfg)
    shield, u = find_shield(env), env.unwrapped
    calls = []
    original = shield._intent

    def spy(others, keys):
        weights = original(others, keys)
        vehicles = [v for v in u.road.vehicles if v is not u.vehicle]
        for row, w in zip(others, weights):
            if np.isfinite(w).all():
                d = [np.hypot(*(v.position - row[0:2])) for v in vehicles]
                v = vehicles[int(np.argmin(d))]
                if not str(v.lane_index[0]).startswith("il"):  # on the exit road the indicator is off, moot
                    calls.append((w, intended_signal(v), min(d)))
        return weights

    shield._intent = spy
    policy = AlwaysProceed(u.cruise_action())
    obs, _ = env.reset(seed=1015)
    for _ in range(60):
        obs, _, term, trunc, _ = env.step(policy.act(obs))
        if term or trunc:
            break
    near = [(w, turn) for w, turn, d in calls if d < 1.0]
    assert len(near) > 50 and len({turn for _, turn in near}) >= 2  # several cars, more than one intent
    assert all(int(np.argmax(w)) == int(turn) + 1 for w, turn in near)  # TURNS: right, straight, left
