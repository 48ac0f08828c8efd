"""cae_lcd.core.checks: the one home of id, timestamp, pose, intrinsics and depth checks (API, CLI and server alike), on
real KITTI poses and intrinsics of the bundled sample."""

from __future__ import annotations

import io

import numpy as np
import pytest

from cae_lcd.core.checks import (MAX_FRAME_ID, check_frame_id, check_intrinsics, check_pose, check_rigid_pose,
                         check_timestamp, decode_depth)
from cae_lcd.core.errors import ConfigError


def npy(array) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


def npy_header_only(shape, dtype="<f8") -> bytes:
    """A .npy whose header declares ``shape`` but carries no data (what an attacker sends)."""
    header = repr({"descr": dtype, "fortran_order": False, "shape": tuple(shape)}).encode()
    header += b" " * (63 - (len(header) + 10) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header


class TestIds:
    @pytest.mark.parametrize("value", [0, 7, np.int64(12), MAX_FRAME_ID - 1])
    def test_accepted(self, value):
        assert check_frame_id(value) == int(value)

    @pytest.mark.parametrize("value", [-1, MAX_FRAME_ID, 2**63, 2**63 - 1, 1e30, 3.0, "16", True, None])
    def test_refused_with_one_line(self, value):
        with pytest.raises(ConfigError, match="frame id") as err:
            check_frame_id(value)
        assert "\n" not in str(err.value)


class TestTimestamps:
    @pytest.mark.parametrize("value", [float("nan"), float("inf"), 1e30, -1e30, "1.0", True])
    def test_refused(self, value):
        with pytest.raises(ConfigError, match="timestamp"):
            check_timestamp(value)

    def test_accepted(self):
        assert check_timestamp(1.7e9) == 1.7e9 and check_timestamp(np.float32(0.5)) == 0.5


class TestPoses:
    def test_real_kitti_poses_are_rigid(self, sample_poses):
        for p in sample_poses[::10]:
            M = check_rigid_pose(p)
            assert M.shape == (4, 4) and np.allclose(M[:3], p, atol=1e-5)

    @pytest.mark.filterwarnings("error")  # 1e200: R^T R overflowed with a RuntimeWarning on the server's stderr
    @pytest.mark.parametrize("scale", [1e-100, 1e100, 1e200, 2.0])
    def test_a_scaled_rotation_is_not_rigid(self, sample_poses, scale):
        p = sample_poses[5].copy()
        p[:, :3] *= scale
        with pytest.raises(ConfigError, match="rotation"):
            check_rigid_pose(p)

    def test_a_reflection_far_translation_and_bad_last_row_are_refused(self, sample_poses):
        p = sample_poses[5].copy()
        p[:, 0] *= -1
        with pytest.raises(ConfigError, match="rotation"):
            check_rigid_pose(p)
        far = sample_poses[5].copy()
        far[:, 3] = 1e300
        with pytest.raises(ConfigError, match="translation"):
            check_rigid_pose(far)
        with pytest.raises(ConfigError, match="0 0 0 1"):
            check_rigid_pose(np.vstack([sample_poses[5], [0, 0, 1, 1]]))

    @pytest.mark.parametrize("value", [[[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0]], np.eye(3), "pose", None])
    def test_malformed_is_refused(self, value):
        with pytest.raises(ConfigError, match="pose"):
            check_rigid_pose(value)
        with pytest.raises(ConfigError, match="pose"):
            check_pose(value)

    def test_check_pose_takes_twelve_numbers_or_4x4(self, sample_poses):
        assert np.array_equal(check_pose(sample_poses[3].ravel()), sample_poses[3])
        assert np.array_equal(check_pose(np.vstack([sample_poses[3], [0, 0, 0, 1]])), sample_poses[3])


class TestIntrinsics:
    def test_the_sample_camera_is_accepted(self, sample_K):
        assert np.array_equal(check_intrinsics(sample_K), sample_K)
        normalised = np.diag([sample_K[0, 0], sample_K[1, 1], 620.0]) / 620.0  # a camera in normalised units
        assert np.array_equal(check_intrinsics(normalised), normalised)

    @pytest.mark.parametrize("K", [np.zeros((3, 3)), -np.eye(3), np.full((3, 3), np.nan), np.eye(4),
                                   [[700, 0, 300], [0, 700, 90], [0, 1, 1]],
                                   # near-singular or enormous: K^-1 or K overflows (a server hung on fx = 1e-300)
                                   [[1e-300, 0, 300], [0, 1e-300, 90], [0, 0, 1]],
                                   [[700, 0, 300], [0, 1e-4, 90], [0, 0, 1]],
                                   [[1e300, 0, 300], [0, 1e300, 90], [0, 0, 1]],
                                   [[700, 1e300, 300], [0, 700, 90], [0, 0, 1]],
                                   [[700, 0, -1e300], [0, 700, 90], [0, 0, 1]]])
    def test_refused(self, K):
        with pytest.raises(ConfigError, match="intrinsics"):
            check_intrinsics(K)


class TestDepth:
    def test_a_real_shaped_depth_map_is_read(self):
        depth = np.full((188, 620), 7.5, np.float32)
        assert np.array_equal(decode_depth(npy(depth), (188, 620)), depth)

    def test_a_huge_declared_shape_is_refused_before_any_allocation(self):
        with pytest.raises(ConfigError, match=r"\(100000, 100000\)"):
            decode_depth(npy_header_only((100000, 100000)), (188, 620))

    def test_a_header_that_lies_about_its_data_is_refused(self):
        with pytest.raises(ConfigError, match="bytes of data"):
            decode_depth(npy_header_only((188, 620)), (188, 620))

    @pytest.mark.parametrize("fill", [np.nan, -1e30, np.inf, 1e30])
    def test_non_finite_or_out_of_range_values_are_refused(self, fill):
        with pytest.raises(ConfigError, match="finite"):
            decode_depth(npy(np.full((188, 620), fill)), (188, 620))

    @pytest.mark.parametrize("data", [b"", b"not npy", npy(np.array(["a"] * 4).reshape(2, 2))])
    def test_not_numeric_npy_is_refused(self, data):
        with pytest.raises(ConfigError, match="depth"):
            decode_depth(data, (2, 2))
