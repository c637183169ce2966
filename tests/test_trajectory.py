"""The trajectory beyond tracking: place recognition (RANSAC + Umeyama on keypoint matches,
retrieval by descriptor), relocalisation of a kidnapped camera, loop closure on a drifted loop
and the refusal of a false one, covisibility edges (candidates, alignment, a drifted path held
back), on the built-in scene. Tests that need the DINOv2 encoder skip when it is not cached
(`legslam models fetch`)."""

import numpy as np
import pytest

from legslam.datasets import open as open_dataset, synthetic
from legslam.eval import ate
from legslam.slam import SLAM, SLAMConfig
from legslam.slam.covisibility import Covisibility
from legslam.slam.keyframes import rotation_deg
from legslam.eval.trajectory import umeyama
from legslam.slam.place_recognition import (Place, PlaceIndex, global_descriptor, keypoints,
                                            overlap, ransac_rigid, ratio_matches, rigid_fits)
from legslam.slam.trajectory import View
from legslam.tracking import Tracker

W, H = 160, 120


def rotation(axis, degrees) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(degrees)
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k


@pytest.fixture(scope="module")
def encoder():
    """The encoder a SLAM run uses by default (places are recognised from its tokens)."""
    from conftest import slam_encoder
    from legslam.features import Encoder

    return Encoder(slam_encoder(), input_size=224, threads=1)


@pytest.fixture(scope="module")
def room():
    """The built-in scene's room, and a renderer of it at any pose (rgb, depth float32)."""
    rng = np.random.default_rng(3)
    parts, textures = synthetic.build_scene(rng), synthetic.Textures(rng)
    K = synthetic.intrinsics(W, H)

    def view(pose):
        rgb, depth, _ = synthetic.render(parts, textures, K, pose, W, H)
        return rgb, depth.astype(np.float32)
    return K, view


def looking(position, target) -> np.ndarray:
    """A camera at `position` looking at `target` (OpenCV axes, z up in the world)."""
    z = np.asarray(target, float) - position
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    T[:3, 3] = position
    return T


def turn_in_place(n: int, degrees_per_frame: float, centre=(0.8, 0.6, 1.3)) -> np.ndarray:
    """A camera turning about the vertical on a small circle (radius 0.15 m) round `centre`."""
    poses = []
    for i in range(n):
        a = np.radians(degrees_per_frame * i)
        d = np.array([np.cos(a), np.sin(a), -0.25])
        poses.append(looking(np.asarray(centre) + 0.15 * np.array([np.cos(a), np.sin(a), 0]),
                             np.asarray(centre) + d))
    return np.stack(poses)


# --- coarse alignment and retrieval -----------------------------------------------------------

def test_ransac_umeyama_recovers_a_known_transform_from_matches_with_outliers():
    rng = np.random.default_rng(0)
    src = rng.uniform(-1, 1, (120, 3)) + [0, 0, 2.5]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rotation([0.3, 1, 0.2], 35), [0.4, -0.2, 0.3]
    dst = src @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.003, src.shape)
    outlier = rng.random(len(src)) < 0.45
    dst[outlier] = rng.uniform(-1, 1, (outlier.sum(), 3)) + [0, 0, 2.5]
    found, inliers = ransac_rigid(src, dst, threshold=0.02)
    assert rotation_deg(found, T) < 0.5
    assert np.linalg.norm(found[:3, 3] - T[:3, 3]) < 0.01
    # The inliers are the true matches (an outlier may land near its true place by chance).
    assert inliers[~outlier].mean() > 0.95 and inliers[outlier].mean() < 0.05
    # A plain least-squares fit over every match is far off: RANSAC is what finds it.
    from legslam.eval import umeyama
    R, _, _ = umeyama(src, dst)
    plain = np.eye(4)
    plain[:3, :3] = R
    assert rotation_deg(plain, T) > 2
    assert ransac_rigid(src[:2], dst[:2], 0.02)[0] is None


def test_rigid_fits_are_umeyamas_fit_of_each_set():
    rng = np.random.default_rng(4)
    src = rng.normal(size=(50, 4, 3))
    # Half the sets moved rigidly, half moved by a reflection (its best rotation is no mirror).
    dst = src @ rotation([1, 2, 3], 70).T + [0.3, -0.2, 1.0]
    dst[25:, :, 0] *= -1
    dst += 0.01 * rng.normal(size=dst.shape)
    R, t = rigid_fits(src, dst)
    for k in range(len(src)):
        R_ref, t_ref, _ = umeyama(src[k], dst[k])
        assert np.allclose(R[k], R_ref, atol=1e-9) and np.allclose(t[k], t_ref, atol=1e-9)
    assert np.allclose(np.linalg.det(R), 1.0)


def test_ratio_matches_keep_only_clearly_nearest_descriptors():
    rng = np.random.default_rng(2)
    b = rng.integers(0, 256, size=(50, 32), dtype=np.uint8)
    b[7] = b[3]
    b[7, 0] ^= np.uint8(1)  # b3 and b7 one bit apart: a row near both is ambiguous
    a = b[[10, 20, 3]].copy()
    a[0, :4] ^= np.uint8(0xFF)  # 32 of 256 bits flipped: still far nearer b10 than any other
    a[2, 1] ^= np.uint8(0xFF)  # 8 bits from b3, 9 from b7: not clearly either
    assert ratio_matches(a, b, 0.8).tolist() == [[0, 10], [1, 20]]
    assert ratio_matches(a[:0], b, 0.8).shape == (0, 2)
    assert ratio_matches(a, b[:1], 0.8).shape == (0, 2)  # no second nearest to compare with


def test_keypoints_are_lifted_with_the_depth_under_them(scene):
    f = scene[12]
    rgb, depth, K = f.rgb, f.depth.copy(), f.K
    depth[:, : W // 2] = 0  # no depth on the left half: no keypoints there
    points, features = keypoints(rgb, depth, K)
    assert len(points) >= 50 and features.shape == (len(points), 32) and features.dtype == np.uint8
    u = points[:, 0] / points[:, 2] * K[0, 0] + K[0, 2]
    v = points[:, 1] / points[:, 2] * K[1, 1] + K[1, 2]
    assert (u >= W // 2 - 0.5).all()
    z = depth[np.rint(v).astype(int), np.rint(u).astype(int)]
    assert np.allclose(points[:, 2], z)


def test_overlap_is_the_share_of_pixels_both_views_see():
    # A wall 2 m ahead; the other camera 1 m to the side sees the half of it nearer to it.
    K = np.array([[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]])
    wall = np.full((H, W), 2.0, np.float32)
    side = np.eye(4)
    side[0, 3] = 2.0 * (W / 2) / K[0, 0]  # half the image width at the wall's depth
    assert overlap(wall, K, np.eye(4), View(np.eye(4), None, wall)) == 1.0
    assert abs(overlap(wall, K, np.eye(4), View(side, None, wall)) - 0.5) < 0.02
    holed = wall.copy()
    holed[:, : W // 2] = 0  # the other view has no depth where it would see the wall
    assert overlap(wall, K, np.eye(4), View(side, None, holed)) < 0.02
    behind = np.eye(4)
    behind[:3, :3] = rotation([0, 1, 0], 180)  # looking away: nothing in front of it
    assert overlap(wall, K, np.eye(4), View(behind, None, wall)) == 0.0
    assert overlap(np.zeros_like(wall), K, np.eye(4), View(np.eye(4), None, wall)) == 0.0


def test_retrieval_ranks_the_revisited_keyframe_first(encoder, room):
    K, view = room
    path = turn_in_place(8, 45.0)  # eight keyframes looking all round the room
    tracker = Tracker(levels=3, finest_level=0)
    index = PlaceIndex(SLAMConfig(place_min_similarity=0.0, place_candidates=8), tracker, K)
    for k, pose in enumerate(path):
        rgb, depth = view(pose)
        index.add(Place.of(k, encoder.encode(rgb), View(pose, rgb, depth), K))
    for k in (2, 5):
        # Back near keyframe k: moved 5 cm and turned 8 degrees.
        revisit = path[k].copy()
        revisit[:3, :3] = rotation([0, 0, 1], 8) @ revisit[:3, :3]
        revisit[:3, 3] += [0.05, -0.03, 0.0]
        rgb, depth = view(revisit)
        query = Place.of(-1, encoder.encode(rgb), View(None, rgb, depth), K)
        ranked = index.candidates(query.descriptor)
        assert ranked[0][0] == k, ranked
        # And verified: the coarse alignment and the tracker place it.
        found = index.verify(query, index.places[k])
        assert found is not None
        assert np.linalg.norm(found.pose[:3, 3] - revisit[:3, 3]) < 0.03
        assert rotation_deg(found.pose, revisit) < 1.5
        # Turned 30 degrees away: the keyframe sees about half of the view. Its inliers are
        # counted among the pixels both see (half of all: an alignment this right was refused
        # when they were counted among all).
        turned = path[k].copy()
        turned[:3, :3] = rotation([0, 0, 1], 30) @ turned[:3, :3]
        turned[:3, 3] += [0.1, -0.1, 0.0]
        rgb, depth = view(turned)
        found = index.verify(Place.of(-1, encoder.encode(rgb), View(None, rgb, depth), K),
                             index.places[k])
        assert found is not None and found.overlap < 0.6 and found.overlap * found.inlier_ratio < 0.5
        assert np.linalg.norm(found.pose[:3, 3] - turned[:3, 3]) < 0.01
        assert rotation_deg(found.pose, turned) < 0.5
    # A view of another part of the room does not verify against keyframe 2's place.
    rgb, depth = view(path[6])
    other = Place.of(-1, encoder.encode(rgb), View(None, rgb, depth), K)
    assert index.verify(other, index.places[2]) is None
    # The descriptor is the normalised mean of unit tokens.
    t = np.random.default_rng(1).normal(size=(4, 4, 8))
    d = global_descriptor(t)
    assert np.isclose(np.linalg.norm(d), 1)


# --- relocalisation ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def scene():
    return open_dataset(synthetic.default_scene(n_frames=60, width=W, height=H, seed=3))


def run_frames(slam, frames):
    return [slam.step(f.rgb, f.depth) for f in frames]


def test_a_kidnapped_camera_is_relocalised_within_a_few_frames(encoder, scene):
    # Frames 0-44, then the camera is carried back to frame 12's place (a jump of about 0.6 m
    # and 20 degrees): 45 + 25 frames.
    order = list(range(45)) + list(range(12, 37))
    frames = [scene[i] for i in order]
    cfg = SLAMConfig(features=False, final_iters=0, loop_closure=False)
    slam = SLAM(cfg, scene[0].K, W, H, encoder=encoder)
    steps = run_frames(slam, frames)
    states = [s.state for s in steps]
    assert "lost" not in states[:45]
    back = states.index("relocalised")
    assert 45 <= back <= 45 + 3, states[40:60]
    assert "lost" not in states[back:], states[back:]
    assert len(slam.relocaliser.events) == 1 and slam.relocaliser.events[0].frame == back
    gt = np.stack([f.pose for f in frames])
    est = np.stack(slam.poses)
    tracked = np.array([s != "lost" for s in states])
    # One alignment fits the frames before and after the jump: the camera came back into the
    # map's frame. Over all frames, the few lost ones (kept where the camera was lost) add
    # what remains.
    assert ate(gt[tracked], est[tracked])["rmse"] < 0.02
    assert ate(gt[back:], est[back:])["rmse"] < 0.02
    assert ate(gt, est)["rmse"] < 0.1


def test_frames_during_a_loss_do_not_change_the_map(scene):
    # A covered lens (dark, no depth), then a view far from the map (beyond the tracker's
    # basin, caught by its residual's jump): every such frame is lost, and the map, its
    # keyframes and its places stay as they were.
    cfg = SLAMConfig(features=False, final_iters=0, loop_closure=False)
    slam = SLAM(cfg, scene[0].K, W, H, encoder=StubEncoder())
    run_frames(slam, [scene[i] for i in range(20)])
    slam.relocaliser.lost = lambda *a: None  # nothing recognised: the loss goes on
    before = slam.gaussian_map()
    keyframes = list(slam.keyframe_frames)
    covered = np.zeros_like(scene[0].rgb), np.zeros_like(scene[0].depth)
    far = scene[55]
    steps = [slam.step(*covered) for _ in range(3)] + [slam.step(far.rgb, far.depth) for _ in range(3)]
    assert [s.state for s in steps] == ["lost"] * 6, [(s.state, s.reason) for s in steps]
    after = slam.gaussian_map()
    assert len(after.means) == len(before.means)
    assert np.array_equal(after.means, before.means) and np.array_equal(after.sh, before.sh)
    assert slam.keyframe_frames == keyframes


class StubEncoder:
    """Stands in for the encoder where no place is to be recognised."""

    dim = 384

    def encode(self, rgb):
        return np.random.default_rng(0).normal(size=(4, 4, 8)).astype(np.float32)


# --- loop closure -----------------------------------------------------------------------------

class Drifting:
    """Wraps a tracking policy: each tracked pose moves a little further off (a yaw and a
    sideways step per frame, compounding), as a drifting odometry would."""

    def __init__(self, policy, degrees: float, metres: float):
        self.policy, self.count = policy, 0
        self.step = np.eye(4)
        self.step[:3, :3] = rotation([0, 0, 1], degrees)
        self.step[:3, 3] = [metres, 0, 0]

    def track(self, *args, **kwargs):
        t = self.policy.track(*args, **kwargs)
        if t.state != "ok":
            return t
        self.count += 1
        return type(t)(self.step @ t.pose, t.state, t.coverage, t.reason)


def drifted_loop(encoder, room, loop_closure: bool, frames: int = 84, covisibility_edges: int = 0):
    K, view = room
    path = turn_in_place(frames, 360.0 / 72)  # a full turn and a bit more
    # Frame to frame only (never the map nor the fused surface: either would take the drift
    # back by itself on return).
    cfg = SLAMConfig(features=False, final_iters=0, loop_closure=loop_closure, relocalise=False,
                     min_reference_coverage=1.0, covisibility_edges=covisibility_edges,
                     surface_voxel=0)
    slam = SLAM(cfg, K, W, H, encoder=encoder)
    slam.tracking = Drifting(slam.tracking, 0.03, 0.001)
    for pose in path:
        rgb, depth = view(pose)
        slam.step(rgb, depth)
    slam.finish(train=False)
    return slam, path


def test_a_drifted_loop_is_closed_and_brought_back(encoder, room):
    slam, gt = drifted_loop(encoder, room, loop_closure=True)
    open_loop, _ = drifted_loop(encoder, room, loop_closure=False)
    est, est_open = np.stack(slam.poses), np.stack(open_loop.poses)
    events = slam.loops.events
    assert events, "no loop closed"
    assert all(e.new - e.old >= slam.config.loop_min_gap for e in events)
    # The drift the wrapper injected (a few cm and degrees by the end) is mostly gone: the
    # end of the loop sits on its start again.
    err, err_open = ate(gt, est)["rmse"], ate(gt, est_open)["rmse"]
    assert err < 0.5 * err_open and err < 0.02, (err, err_open)
    # The map moved with its keyframes: keyframe poses in the mapper are the graph's.
    assert np.allclose(slam.mapper.keyframe_poses(), np.stack(slam.loops.poses), atol=1e-6)


def straight_chain(loops, n: int):
    """`loops` (a LoopClosure) with n keyframes 10 cm apart in a line, each tracked after the
    one before."""
    step = np.eye(4)
    step[:3, 3] = [0.1, 0, 0]
    pose = np.eye(4)
    for k in range(n):
        loops.add_keyframe(frame=10 * k, pose=pose, after=k - 1 if k else None)
        pose = pose @ step
    return loops


def test_a_false_loop_is_rejected_and_logged(room, caplog):
    """Two places that look alike (the same view) but are 1 m apart in the graph: the loop
    edge between them contradicts the odometry and is dropped, the poses stay."""
    from legslam.slam.loop_closure import LoopClosure
    from legslam.slam.place_recognition import Recognised

    loops = straight_chain(LoopClosure(SLAMConfig(loop_min_gap=3), places=None), 10)
    before = np.stack(loops.poses)
    # Keyframe 9 "recognised" at keyframe 0's place, as twin rooms would make it.
    false = Recognised(pose=loops.poses[0], keyframe=0, similarity=0.95, inliers=40, matches=60,
                       inlier_ratio=0.8, overlap=0.9)
    with caplog.at_level("WARNING", logger="legslam"):
        assert loops.close(9, false, ms=0.0) is None
    assert "rejected" in caplog.text
    assert loops.rejected and loops.rejected[0]["keyframes"] == [0, 9]
    assert not loops.events and np.allclose(np.stack(loops.poses), before)
    assert all(e.kind == "odometry" for e in loops.graph.edges)


def test_a_loop_the_later_edges_contradict_is_marked_dropped(caplog):
    """A loop closed at first (8 cm off the odometry of 90 cm) that the next keyframe's
    covisibility edges contradict is dropped by that optimisation: metrics.json marks it with the
    frame it was dropped at, and it no longer counts among the loops that hold."""
    from legslam.slam.covisibility import Covisible
    from legslam.slam.loop_closure import LoopClosure
    from legslam.slam.place_recognition import Recognised
    from legslam.slam.pose_graph import relative

    loops = straight_chain(LoopClosure(SLAMConfig(loop_min_gap=3), places=None), 10)
    chain = [p.copy() for p in loops.poses]
    off = chain[9].copy()
    off[1, 3] += 0.08
    found = Recognised(pose=off, keyframe=0, similarity=0.95, inliers=40, matches=60,
                       inlier_ratio=0.8, overlap=0.9)
    assert loops.close(9, found, ms=0.0) is not None
    assert [e.dropped_at_frame for e in loops.events] == [None] and loops.held == loops.events
    # Keyframe 10 (frame 100), a step on from keyframe 9, sees keyframes 0-2 where the chain put them.
    step = relative(chain[8], chain[9])
    loops.add_keyframe(frame=100, pose=loops.poses[9] @ step, after=9)
    ten = chain[9] @ step
    with caplog.at_level("WARNING", logger="legslam"):
        loops.add_covisible([Covisible(new=10, old=k, measurement=relative(ten, chain[k]),
                                       inlier_ratio=0.9, overlap=0.5) for k in (0, 1, 2)])
    assert "dropped at frame 100" in caplog.text
    record = loops.events[0].as_dict()
    assert record["dropped_at_frame"] == 100 and record["frame"] == 90
    assert loops.held == []
    assert loops.rejected == [{"frame": 90, "keyframes": [0, 9], "chi2": loops.rejected[0]["chi2"],
                               "dropped_at_frame": 100}]
    # Without the loop the keyframes go back where the odometry and the new edges put them.
    assert np.allclose(np.stack(loops.poses)[:10, :3, 3], np.stack(chain)[:, :3, 3], atol=5e-3)


def test_the_progress_line_counts_the_loops_that_hold():
    from types import SimpleNamespace

    from legslam.pipeline import _events

    closed = [{"frame": 90, "dropped_at_frame": 100}, {"frame": 120, "dropped_at_frame": None}]
    slam = SimpleNamespace(trajectory_events=lambda: {"relocalisations": [{}],
                                                      "loop_closures": closed})
    assert _events(slam) == "  reloc 1  loops 1"
    closed.pop()
    assert _events(slam) == "  reloc 1"


def test_without_the_encoder_no_features_runs_without_place_recognition(scene, tmp_path, monkeypatch,
                                                                       caplog):
    monkeypatch.setenv("LEGSLAM_CACHE", str(tmp_path))  # no encoder cached there
    with caplog.at_level("WARNING", logger="legslam"):
        slam = SLAM(SLAMConfig(features=False, final_iters=0), scene[0].K, W, H)
    assert "no relocalisation or loop closure" in caplog.text
    assert slam.places is None and slam.relocaliser is None and slam.loops.places is None
    run_frames(slam, [scene[i] for i in range(3)])
    events = slam.trajectory_events()
    assert "relocalisations" not in events and "loop_closures" not in events
    assert "covisibility_edges" in events  # the pose graph needs no encoder
    with pytest.raises(FileNotFoundError):  # language features still need it
        SLAM(SLAMConfig(final_iters=0), scene[0].K, W, H)


def test_each_mode_loads_its_encoder(scene, tmp_path, monkeypatch):
    # "auto": int8 where the encoder competes with a mapping thread for the cores, the full
    # precision one otherwise; a model named in the config is loaded whatever the mode. An
    # empty cache makes the loader name the file it looked for.
    monkeypatch.setenv("LEGSLAM_CACHE", str(tmp_path))
    from legslam.models import DEFAULT_MODEL, INT8_MODEL

    for config, wanted in ((SLAMConfig(final_iters=0), DEFAULT_MODEL),
                           (SLAMConfig(final_iters=0, mapping_thread=True), INT8_MODEL),
                           (SLAMConfig(final_iters=0, encoder="dinov2_vits14_int8"), INT8_MODEL),
                           (SLAMConfig(final_iters=0, mapping_thread=True, encoder="default"),
                            DEFAULT_MODEL)):
        with pytest.raises(FileNotFoundError) as e:
            SLAM(config, scene[0].K, W, H)
        assert f"{wanted} is missing" in str(e.value), (config.encoder, config.mapping_thread, e.value)


# --- covisibility edges -----------------------------------------------------------------------

def test_covisibility_candidates_are_the_older_keyframes_that_see_most_of_the_view():
    # A wall 2 m ahead, 3.2 m of it in view; keyframes beside the new one see less of it the
    # farther they stand, one looks away, and one is the keyframe the new one was tracked after.
    K = np.array([[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]])
    wall = np.full((H, W), 2.0, np.float32)
    rgb = np.zeros((H, W, 3), np.uint8)

    def at(x, turned=False):
        T = np.eye(4)
        T[0, 3] = x
        if turned:
            T[:3, :3] = rotation([0, 1, 0], 180)
        return T
    poses = [at(0.0), at(1.0), at(0.2), at(2.5), at(0.0, turned=True), at(0.0)]
    cov = Covisibility(SLAMConfig(covisibility_edges=2, covisibility_min_overlap=0.3), None, K)
    for _ in poses:
        cov.add(rgb, wall)
    ranked = cov.candidates(5, poses, exclude=0)
    # Keyframe 2 sees 94% of the view, 1 69%; 3 (22%) is below the threshold, 4 faces away.
    assert [k for k, _ in ranked] == [2, 1], ranked
    assert abs(ranked[0][1] - (1 - 0.2 / 3.2)) < 0.05 and abs(ranked[1][1] - (1 - 1.0 / 3.2)) < 0.05
    cov.config = SLAMConfig(covisibility_edges=8, covisibility_min_overlap=0.3)
    assert [k for k, _ in cov.candidates(5, poses, exclude=None)] == [0, 2, 1]
    cov.config = SLAMConfig(covisibility_edges=0)
    assert cov.candidates(5, poses, exclude=None) == []


def test_a_covisibility_edge_measures_the_keyframes_true_relative_pose(room):
    K, view = room
    path = turn_in_place(4, 10.0)
    old_pose, new_pose = path[0], path[2]  # 20 degrees apart round the room
    tracker = Tracker(levels=3, finest_level=0)
    cov = Covisibility(SLAMConfig(covisibility_min_overlap=0.3), tracker, K)
    for pose in (old_pose, new_pose):
        cov.add(*view(pose))
    # The old keyframe's pose is off by 3 cm and 1.5 degrees, as a chain of alignments leaves it.
    drifted = old_pose.copy()
    drifted[:3, :3] = rotation([0.3, 0.2, 1], 1.5) @ drifted[:3, :3]
    drifted[:3, 3] += [0.02, -0.02, 0.01]
    (edge,) = cov.edges(1, [drifted, new_pose])
    assert (edge.new, edge.old) == (1, 0) and edge.inlier_ratio > 0.65 and edge.overlap > 0.5
    truth = np.linalg.inv(new_pose) @ old_pose
    assert np.linalg.norm(edge.measurement[:3, 3] - truth[:3, 3]) < 0.005
    assert rotation_deg(edge.measurement, truth) < 0.3
    # A keyframe that saw another part of the room, though its pose says it saw this one: the
    # alignment does not verify, and no edge is made.
    cov.add(*view(turn_in_place(8, 45.0)[4]))
    assert cov.edges(2, [drifted, new_pose, old_pose], exclude=1) == []


def test_covisibility_edges_hold_a_drifting_camera_back(encoder, room):
    # The same drifted turn as the loop-closure test, with no loop closure: each keyframe's
    # alignments with the keyframes that see what it sees take most of the drift back.
    with_edges, gt = drifted_loop(encoder, room, loop_closure=False, covisibility_edges=4)
    without, _ = drifted_loop(encoder, room, loop_closure=False)
    err, err_without = ate(gt, np.stack(with_edges.poses))["rmse"], ate(gt, np.stack(without.poses))["rmse"]
    assert err < 0.5 * err_without, (err, err_without)
    assert with_edges.loops.covisible > 0 and not with_edges.loops.events
    events = with_edges.trajectory_events()
    assert events["covisibility_edges"] == with_edges.loops.covisible
    # The map moved with its keyframes.
    assert np.allclose(with_edges.mapper.keyframe_poses(), np.stack(with_edges.loops.poses), atol=1e-6)


def test_a_contradicting_covisibility_edge_is_rejected_and_logged(caplog):
    from legslam.slam.covisibility import Covisible
    from legslam.slam.loop_closure import LoopClosure

    loops = straight_chain(LoopClosure(SLAMConfig(), places=None), 6)
    before = np.stack(loops.poses)
    right = Covisible(5, 3, np.linalg.inv(before[5]) @ before[3], 0.9, 0.8)
    wrong = Covisible(5, 2, np.linalg.inv(before[5]) @ before[0], 0.9, 0.8)  # 30 cm off
    with caplog.at_level("WARNING", logger="legslam"):
        corrections = loops.add_covisible([right, wrong])
    assert "covisibility edge" in caplog.text and "rejected" in caplog.text
    assert loops.covisible == 1 and loops.rejected_covisible[0]["keyframes"] == [2, 5]
    assert not loops.rejected  # no loop edge was involved
    assert np.allclose(corrections @ before, np.stack(loops.poses))
    assert np.allclose(np.stack(loops.poses), before, atol=1e-6)
    assert loops.add_covisible([]) is None
