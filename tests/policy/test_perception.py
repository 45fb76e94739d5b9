"""Object poses perceived from a rendered observation against the simulator's own poses."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.sim
@pytest.mark.slow
def test_perceived_pose_matches_the_simulator_after_the_cube_is_moved_and_turned():
    import sapien

    from datagen.simulate import EpisodeSimulator, SimConfig
    from tesseract4d.policy.perception import CENTRE_TOL_M, FACE_TOL_DEG, ObjectPerception, wrap_quarter

    sim = EpisodeSimulator("StackCube-v1", SimConfig(height=128, width=128, cameras=["close"], frames=1))
    try:
        first = sim.first_frame(100000)
        base = sim.env.unwrapped
        perception = ObjectPerception(sim.observe()["close"], first.cameras["close"].seg_id_to_name)
        assert sorted(perception.names()) == ["cubeA", "cubeB"]

        def truth(actor):
            p = actor.pose.p[0].cpu().numpy().astype(np.float64)
            w, x, y, z = actor.pose.q[0].cpu().numpy().astype(np.float64)
            return p, float(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))

        now = perception.perceive(sim.observe()["close"])
        for name in ("cubeA", "cubeB"):
            p, yaw = truth(getattr(base, name))
            assert np.linalg.norm(now[name].centre_world_m - p) < CENTRE_TOL_M, (name, now[name].centre_world_m, p)
            assert abs(np.rad2deg(wrap_quarter(now[name].face_yaw_rad - yaw))) < FACE_TOL_DEG
        # move cube A 6 cm and turn it by 30 degrees, as a push would; the perception sees only the camera
        p, yaw = truth(base.cubeA)
        new_yaw = yaw + np.deg2rad(30)
        q = [np.cos(new_yaw / 2), 0.0, 0.0, np.sin(new_yaw / 2)]
        base.cubeA.set_pose(sapien.Pose(p=(p + [0.06, -0.03, 0.0]).astype(np.float32), q=q))
        now = perception.perceive(sim.observe()["close"])
        p, yaw = truth(base.cubeA)
        err_m = np.linalg.norm(now["cubeA"].centre_world_m - p)
        err_deg = abs(np.rad2deg(wrap_quarter(now["cubeA"].face_yaw_rad - yaw)))
        assert err_m < CENTRE_TOL_M and err_deg < FACE_TOL_DEG, (err_m, err_deg)
        assert now["cubeA"].seen_px > 20 and now["cubeA"].fit_rms_m < 0.004
    finally:
        sim.close()
