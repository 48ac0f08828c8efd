"""The HDF5 keyframe database: round trips, resumption, refusal of damaged or mismatched files."""

import h5py
import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from cae_lcd.core.errors import DatabaseError
from retrieval.database import FORMAT_VERSION, KeyframeDatabase, KeyframeRecord
from verify.features import Features

CONF = {"policy": {"min_inliers": 30}, "index": {"name": "flat"}}
ENCODER_ID = "0123456789abcdef"


@pytest.fixture(scope="module")
def records(sift_features, sample_seq, encoder, sample_image):
    """Three keyframes of real sample frames (codes, SIFT features, poses, times); the last one has no features."""
    from cae.encode import encode_images

    ids = (3, 7, 12)
    codes = encode_images(encoder, [sample_image(i) for i in ids])
    recs = []
    for n, (i, code) in enumerate(zip(ids, codes)):
        feats = sift_features(i) if n < 2 else Features.empty()
        recs.append(KeyframeRecord(
            frame_id=i, code=code, features=feats, timestamp=float(sample_seq.timestamps[i]),
            pose=sample_seq.poses[i] if n != 1 else None, source=f"{i:06d}.jpg", edge_ratio=0.1 + n,
            candidates=np.array([[0, 0.9, 12, 8, 0.5, 3.0]]) if n == 1 else None, loop=0 if n == 1 else -1))
    return recs


@pytest.fixture()
def db_path(tmp_path, records):
    path = tmp_path / "keyframes.h5"
    with KeyframeDatabase(path, CONF, ENCODER_ID) as db:
        for rec in records:
            db.append(rec)
        db.add_gated(13)
        db.add_gated(14)
    return path


class TestKeyframeDatabase:
    def test_round_trip(self, db_path, records):
        with KeyframeDatabase(db_path, CONF, ENCODER_ID) as db:
            assert len(db) == 3
            assert db.conf == CONF and db.encoder == ENCODER_ID
            back = list(db)
            codes, ids = db.codes()
            np.testing.assert_array_equal(db.gated(), [13, 14])
            assert db.last_frame_id() == 14
        assert [r.frame_id for r in back] == [3, 7, 12]
        np.testing.assert_array_equal(ids, [3, 7, 12])
        for rec, got, code in zip(records, back, codes):
            stored = rec.code.astype(np.float16).astype(np.float32)  # codes are kept at float16 precision
            np.testing.assert_array_equal(got.code, stored)
            np.testing.assert_array_equal(code, stored)
            assert got.code.dtype == np.float32
            kept = rec.features.compact()  # keypoints in 1/8 px, scales float16: what the detector keeps too
            np.testing.assert_array_equal(got.features.keypoints, kept.keypoints)
            np.testing.assert_allclose(got.features.keypoints, rec.features.keypoints, atol=1 / 16)
            np.testing.assert_array_equal(got.features.scales, kept.scales)
            # SIFT descriptors are stored as uint8 (lossless) and come back as equal float32 values
            assert got.features.descriptors.dtype == np.float32
            np.testing.assert_array_equal(got.features.descriptors, rec.features.descriptors)
            assert got.timestamp == rec.timestamp
            assert got.source == rec.source and got.edge_ratio == pytest.approx(rec.edge_ratio)
            assert got.loop == rec.loop
            if rec.pose is None:
                assert got.pose is None
            else:
                np.testing.assert_array_equal(got.pose, rec.pose)
                assert got.pose.shape == (3, 4)
        np.testing.assert_array_equal(back[1].candidates, [[0, 0.9, 12, 8, 0.5, 3.0]])
        assert back[0].candidates.shape == (0, 6)
        # the empty keyframe keeps the right shapes
        assert back[2].features.keypoints.shape == (0, 2) and back[2].features.descriptors.shape == (0, 128)

    def test_poses_nan_where_unknown(self, db_path, records):
        with KeyframeDatabase(db_path, mode="r") as db:
            poses = db.poses()
        assert poses.shape == (3, 3, 4)
        np.testing.assert_array_equal(poses[0], records[0].pose)
        assert records[1].pose is None and np.isnan(poses[1]).all()

    def test_storage_layout(self, db_path, records):
        with h5py.File(db_path, "r") as f:
            assert int(f.attrs["format_version"]) == FORMAT_VERSION == 8
            assert f.attrs["descriptor"] == ENCODER_ID and int(f.attrs["committed"]) == 5
            assert f["frames/frame_id"][:5].tolist() == [3, 7, 12, 13, 14]  # (room for growth past the commit)
            assert f["frames/kind"][:5].tolist() == [0, 0, 0, 1, 1]  # keyframes, then two gated frames
            assert f["codes"].shape[1:] == (4096,) and f["codes"].dtype == np.float16  # one matrix, compact
            n0, n1 = len(records[0].features), len(records[1].features)
            assert f["frames/feat_end"][:5].tolist() == [n0, n0 + n1, n0 + n1, n0 + n1, n0 + n1]  # ragged offsets
            assert f["features/descriptors"].dtype == np.uint8 and f["features/descriptors"].shape[1] == 128
            assert f["features/keypoints"].dtype == np.uint16 and f["features/scales"].dtype == np.float16
            assert f["candidates"].shape[1] == 6 and f.attrs["metric"] == "l2"
            assert len(f["blocks/checksum"][0]) == 32 and "keyframes" not in f  # no group per keyframe
            assert f["blocks/end"][:1].tolist() == [5]  # one checksum for the block of five frames written at close

    def test_float_descriptors_kept_when_not_integral(self, tmp_path, sift_features):
        f = sift_features(3)
        root = Features(f.keypoints, np.sqrt(f.descriptors), f.scales)  # RootSIFT-like, not integral
        with KeyframeDatabase(tmp_path / "r.h5", CONF) as db:
            db.append(KeyframeRecord(0, np.zeros(4096, np.float32), root))
        with KeyframeDatabase(tmp_path / "r.h5", CONF) as db:
            got = next(iter(db))
        assert got.features.descriptors.dtype == np.float32
        np.testing.assert_array_equal(got.features.descriptors, root.descriptors)

    def test_append_after_reopen(self, db_path, records):
        with KeyframeDatabase(db_path, CONF, ENCODER_ID) as db:
            db.append(KeyframeRecord(20, records[0].code, records[0].features))
        with KeyframeDatabase(db_path, CONF, ENCODER_ID, mode="r") as db:
            assert len(db) == 4 and db.last_frame_id() == 20

    def test_empty_database(self, tmp_path):
        with KeyframeDatabase(tmp_path / "e.h5", CONF) as db:
            assert len(db) == 0 and db.last_frame_id() == -1
            assert db.gated().shape == (0,)
            codes, ids = db.codes()
            assert len(codes) == 0 and ids.shape == (0,)
            assert list(db) == []

    def test_different_conf_refused(self, db_path):
        before = db_path.read_bytes()
        with pytest.raises(ConfigError, match="different configuration") as err:
            KeyframeDatabase(db_path, {**CONF, "policy": {"min_inliers": 10}}, ENCODER_ID)
        assert "policy.min_inliers" in str(err.value) and "10 now" in str(err.value)
        assert db_path.read_bytes() == before

    def test_other_encoder_refused(self, db_path):
        with pytest.raises(ConfigError, match="another global descriptor or other weights"):
            KeyframeDatabase(db_path, CONF, "fedcba9876543210")

    def test_truncated_file_refused_and_untouched(self, db_path):
        data = db_path.read_bytes()
        db_path.write_bytes(data[: len(data) // 2])
        before = db_path.read_bytes()
        with pytest.raises(DatabaseError, match="is damaged \\(truncated or corrupt") as err:
            KeyframeDatabase(db_path, CONF, ENCODER_ID)
        assert str(db_path) in str(err.value)
        assert db_path.read_bytes() == before and db_path.stat().st_size == len(data) // 2

    def test_not_hdf5_refused(self, tmp_path):
        path = tmp_path / "notes.h5"
        path.write_text("plain text, not HDF5\n" * 20)
        with pytest.raises(DatabaseError, match="damaged"):
            KeyframeDatabase(path, CONF)
        assert path.read_text().startswith("plain text")

    def test_foreign_hdf5_refused(self, tmp_path):
        path = tmp_path / "other.h5"
        with h5py.File(path, "w") as f:
            f.create_dataset("x", data=np.arange(3))
        with pytest.raises(ConfigError, match="not a keyframe database"):
            KeyframeDatabase(path, CONF)

    @pytest.mark.parametrize("version", [4, 6])  # the group-per-keyframe layout; the one before grey copies
    def test_other_format_version_refused(self, db_path, version):
        with h5py.File(db_path, "a") as f:
            f.attrs["format_version"] = version
        before = db_path.read_bytes()
        with pytest.raises(ConfigError, match=f"format_version {version}; this software reads 8") as err:
            KeyframeDatabase(db_path, CONF, ENCODER_ID)
        assert "\n" not in str(err.value) and db_path.read_bytes() == before  # one line, the file as it was

    @staticmethod
    def _half_write(path, code):
        """What a kill between writing a frame's arrays and its commit leaves: longer arrays, same ``committed``."""
        with h5py.File(path, "a") as f:
            n, k = int(f.attrs["committed"]), int(f["frames/code_end"][int(f.attrs["committed"]) - 1])
            for name, pos, row in (("codes", k, code.astype(np.float16)), ("frames/frame_id", n, 20)):
                f[name].resize(max(len(f[name]), pos + 1), axis=0)
                f[name][pos] = row

    def test_half_written_keyframe_dropped_on_resume(self, db_path, records):
        self._half_write(db_path, records[0].code)
        with KeyframeDatabase(db_path, CONF, ENCODER_ID) as db:
            assert len(db) == 3 and db.last_frame_id() == 14
            assert [r.frame_id for r in db] == [3, 7, 12]
            db.append(KeyframeRecord(21, records[1].code, records[1].features))
        with h5py.File(db_path, "r") as f:
            assert f["frames/frame_id"][:6].tolist() == [3, 7, 12, 13, 14, 21] and int(f.attrs["committed"]) == 6
        with KeyframeDatabase(db_path, mode="r") as db:
            assert db.codes()[1].tolist() == [3, 7, 12, 21]
            np.testing.assert_array_equal(db.features(21).descriptors, records[1].features.descriptors)

    def test_half_written_keyframe_invisible_read_only(self, db_path, records):
        self._half_write(db_path, records[0].code)
        with KeyframeDatabase(db_path, mode="r") as db:
            assert len(db) == 3
            assert [r.frame_id for r in db] == [3, 7, 12]
            assert db.codes()[1].tolist() == [3, 7, 12]

    @pytest.mark.parametrize("dataset, read", [
        ("codes", lambda db: db.codes()),
        ("candidates", lambda db: list(db.results())),
        ("frames/loop", lambda db: list(db)),
        ("features/descriptors", lambda db: db.features(3)),
        ("features/keypoints", lambda db: db.features(3)),
    ])
    def test_damage_caught_by_checksum(self, db_path, dataset, read):
        with h5py.File(db_path, "a") as f:  # one value changed in place, as a bit flip on disk would
            ds = f[dataset]
            row = ds[0] if ds.ndim == 1 else ds[0].copy()
            if ds.ndim == 1:
                ds[0] = row + 1
            else:
                row.flat[0] = row.flat[0] + 1
                ds[0] = row
        with KeyframeDatabase(db_path, mode="r") as db:
            with pytest.raises(DatabaseError, match="damaged.*checksum"):
                read(db)

    def test_other_rows_readable_after_damage(self, db_path, records):
        with h5py.File(db_path, "a") as f:
            last = int(f["frames/feat_end"][1]) - 1  # the last descriptor of keyframe 7
            f["features/descriptors"][last, 0] += 1
        with KeyframeDatabase(db_path, mode="r") as db:
            np.testing.assert_array_equal(db.features(3).descriptors, records[0].features.descriptors)
            with pytest.raises(DatabaseError, match="frame 7 fail"):
                db.features(7)
            with pytest.raises(KeyError):
                db.features(13)  # gated: no keyframe

    def test_read_mode_on_missing_file(self, tmp_path):
        with pytest.raises(ConfigError):
            KeyframeDatabase(tmp_path / "missing.h5", mode="r")
        assert not (tmp_path / "missing.h5").exists()


_KILLED_WRITER = """
import os, sys, numpy as np
from retrieval.database import KeyframeDatabase, KeyframeRecord
from verify.features import Features
rng = np.random.default_rng(0)
db = KeyframeDatabase(sys.argv[1], {}, "x", flush_every=int(sys.argv[2]))
for i in range(int(sys.argv[3])):
    f = Features(rng.uniform(0, 500, (20, 2)).astype(np.float32), rng.integers(0, 256, (20, 128)).astype(np.float32),
                 rng.uniform(1, 9, 20).astype(np.float32))
    db.append(KeyframeRecord(i, rng.standard_normal(8).astype(np.float32), f, float(i), source=f"{i}.png",
                             candidates=np.array([[max(0, i - 1), 0.5, 3, 2, 0.1, 1.0]]), loop=i - 1))
    if i % 3 == 2:
        db.add_gated(1000 + i)  # ids must increase: gated ids go far above, then the keyframes stop
        break
os._exit(0)  # as a kill -9: nothing closed, nothing flushed
"""


class TestWriteAheadLog:
    """Each frame is in the write-ahead log when ``append`` returns; the columns get it a block at a time."""

    @staticmethod
    def _write(path, flush_every, n):
        import subprocess
        import sys
        subprocess.run([sys.executable, "-c", _KILLED_WRITER, str(path), str(flush_every), str(n)], check=True)

    def test_killed_writer_loses_nothing(self, tmp_path):
        self._write(tmp_path / "a.h5", 1000, 3)  # killed with every frame still only in the log
        self._write(tmp_path / "b.h5", 1, 3)  # every frame in the columns at once
        assert (tmp_path / "a.h5.log").stat().st_size > 0
        with KeyframeDatabase(tmp_path / "a.h5", {}, "x") as a, KeyframeDatabase(tmp_path / "b.h5", {}, "x") as b:
            assert [e.frame_id for e in a.frames()] == [e.frame_id for e in b.frames()] == [0, 1, 2, 1002]
            for ra, rb in zip(a, b):
                np.testing.assert_array_equal(ra.code, rb.code)
                np.testing.assert_array_equal(ra.features.descriptors, rb.features.descriptors)
                np.testing.assert_array_equal(ra.candidates, rb.candidates)
                assert (ra.source, ra.loop, ra.timestamp) == (rb.source, rb.loop, rb.timestamp)
        assert not (tmp_path / "a.h5.log").exists()  # taken into the columns, then removed

    def test_torn_log_record_dropped(self, tmp_path):
        self._write(tmp_path / "a.h5", 1000, 3)
        log = tmp_path / "a.h5.log"
        log.write_bytes(log.read_bytes()[:-5])  # the last frame's record torn by the kill
        with KeyframeDatabase(tmp_path / "a.h5", {}, "x") as db:
            assert [e.frame_id for e in db.frames()] == [0, 1, 2]
            db.append(KeyframeRecord(3, np.ones(8, np.float32), Features.empty()))  # and the run goes on
        with KeyframeDatabase(tmp_path / "a.h5", mode="r") as db:
            assert db.last_frame_id() == 3 and len(db) == 4

    def test_pending_features_read_back(self, tmp_path, records):
        with KeyframeDatabase(tmp_path / "p.h5", CONF, flush_every=100) as db:
            db.append(records[0])
            assert int(db.file.attrs["committed"]) == 0  # still in the log only
            np.testing.assert_array_equal(db.features(records[0].frame_id).descriptors,
                                          records[0].features.descriptors)


class TestOnlineState:
    """The online calibration's state kept beside the blocks (``write_online`` / ``online_state``)."""

    ARRAYS = {"frame_id": np.array([3, 7], np.int64), "calibration": np.frombuffer(b"\x01\x02", np.uint8)}

    def test_newest_complete_state_the_frames_reach(self, db_path):
        with KeyframeDatabase(db_path, CONF, ENCODER_ID) as db:
            assert db.online_state(12) is None
            db.write_online(3, {"ready": False}, self.ARRAYS)
            db.write_online(7, {"ready": True}, self.ARRAYS)
            db.write_online(7, {"ready": True, "again": 1}, self.ARRAYS)  # a resumed run refitting there: replaced
            db.write_online(20, {"ready": True}, self.ARRAYS)  # past the stored frames (a lost log): not taken
            np.testing.assert_array_equal(db.edge_ratios(), [0.1, 1.1, 2.1])
        with h5py.File(db_path, "a") as f:
            del f["online/7"].attrs["checksum"]  # half-written by a killed run
        with KeyframeDatabase(db_path, CONF, ENCODER_ID, mode="r") as db:
            fid, meta, arrays = db.online_state(db.last_frame_id())
        assert fid == 3 and meta == {"ready": False}
        assert {k: v.tolist() for k, v in arrays.items()} == {k: v.tolist() for k, v in self.ARRAYS.items()}

    def test_damaged_state_is_reported(self, db_path):
        with KeyframeDatabase(db_path, CONF, ENCODER_ID) as db:
            db.write_online(7, {"ready": True}, self.ARRAYS)
        with h5py.File(db_path, "a") as f:
            f["online/7/frame_id"][0] = 4  # a bit flip
        with KeyframeDatabase(db_path, CONF, ENCODER_ID) as db:
            with pytest.raises(DatabaseError, match="online calibration state of keyframe 7 fails its checksum"):
                db.online_state(12)
