"""``python -m bench.store_open`` on a small store: reopened, read back, and its graph index restored whole."""

from bench.store_open import main


def test_small_store_reopens_and_restores_its_index(tmp_path):
    res = main(keyframes=300, out=tmp_path / "so", features=10, index="hnsw")
    assert res["keyframes"] == 300  # every code and candidate row read back, checksums verified
    assert res["index_bytes"] > 300 * 256 * 2  # the graph and its float16 codes (index.storage: fp16)
    assert res["index_restore_s"] < res["index_build_s"] + 1.0
