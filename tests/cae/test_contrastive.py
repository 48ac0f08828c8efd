"""The place term (issue 28): on real frames it pulls two views of one frame together and pushes other frames away;
the sampling of positives and negatives follows the folder order; the views keep shapes and ranges."""

import numpy as np
import pytest
import torch

import cae.train as training
from cae.contrastive import code_anchor, far_mask, info_nce, neighbour_partners
from cae.model import ConvAutoencoder
from cae.train import _Frames, _place_step, _view, default_conf, sequence_order
from cae_lcd.core.conf import merge_conf
from cae_lcd.core.images import read_image
from cae.preprocess import to_network_u8

FRAMES = [0, 20, 40, 60, 80, 98]  # sample frames far apart: different places


@pytest.fixture(scope="module")
def real_frames(copy_sample_frames, tmp_path_factory):
    """6 real frames of the bundled sample, at the network size, one folder in time order."""
    folder = tmp_path_factory.mktemp("contrastive")
    paths = copy_sample_frames(FRAMES, folder)
    images = np.stack([to_network_u8(read_image(p)) for p in paths])
    return _Frames(images, *sequence_order(paths))


def view_margin(model, frames, seed):
    """The worst frame's margin: cosine (centred codes) between its two views minus that between its first view and
    the nearest view of another frame (what retrieval needs: the other view ranked first); views from ``seed``."""
    conf = merge_conf(default_conf, {})
    rng = np.random.default_rng(seed)
    x = training._to_batch(frames.images, torch.device("cpu"))
    with torch.no_grad():
        a, b = (model.encoder.forward_map(_view(x, rng, conf)[1]).flatten(1) for _ in range(2))
    z = torch.cat([a, b])
    z = torch.nn.functional.normalize(z - z.mean(0, keepdim=True), dim=1)
    sims = (z[:len(a)] @ z[len(a):].T).numpy()
    others = np.where(np.eye(len(a), dtype=bool), -np.inf, sims)
    return float((np.diag(sims) - others.max(1)).min())


def train_steps(frames, contrastive, steps=6):
    torch.manual_seed(0)
    model = ConvAutoencoder()
    optim = torch.optim.Adam(model.parameters(), lr=2e-3)
    conf = merge_conf(default_conf, {"contrastive": contrastive, "far": 2, "neighbours": 0, "recon_share": 0.25})
    before = view_margin(model, frames, seed=0)
    for _ in range(steps):
        rng = np.random.default_rng(0)  # the same two views every step (as view_margin(seed=0) draws them)
        optim.zero_grad()
        if contrastive:  # its gradient accumulated by the step itself
            _place_step(model, frames, np.arange(len(frames)), rng, conf, torch.device("cpu"),
                        np.zeros((0, 2), np.int64))
        else:  # the same step without the place term: reconstruction of the same views only
            target, view = _view(training._to_batch(frames.images, torch.device("cpu")), rng, conf)
            torch.nn.functional.binary_cross_entropy_with_logits(model(view[:2]), target[:2]).backward()
        optim.step()
    return before, view_margin(model, frames, seed=0)


def test_place_term_pulls_views_of_one_frame_together(real_frames):
    """A few steps on 6 real frames: the worst frame's two (strongly changed) views end nearer to each other than
    to any other frame's view by a wider margin; reconstruction alone does not do that (the test goes red without
    the place term)."""
    before, after = train_steps(real_frames, contrastive=1.0)
    _, recon_only = train_steps(real_frames, contrastive=0.0)
    assert after > before + 0.2, (before, after)
    assert after > recon_only + 0.2, (after, recon_only)


def test_info_nce_prefers_the_partner():
    g = torch.Generator().manual_seed(0)
    a = torch.randn(6, 32, generator=g)
    neg = torch.as_tensor(far_mask(np.zeros(6, int), np.arange(6) * 10, 5))
    same = info_nce(a, a + 0.01 * torch.randn(6, 32, generator=g), neg, 0.1)
    shuffled = info_nce(a, a[torch.tensor([1, 2, 3, 4, 5, 0])], neg, 0.1)
    assert same < 0.1 < shuffled
    assert info_nce(a[:0], a[:0], neg[:0, :0], 0.1) == 0


def test_code_anchor_measures_how_far_codes_moved():
    g = torch.Generator().manual_seed(0)
    teacher = torch.rand(6, 32, generator=g)
    assert float(code_anchor(teacher.clone(), teacher)) == pytest.approx(0, abs=1e-6)
    near = code_anchor(teacher + 0.01 * torch.randn(6, 32, generator=g), teacher)
    far = code_anchor(torch.rand(6, 32, generator=g), teacher)
    assert 0 < near < 0.01 < far
    assert float(code_anchor(3 * (teacher - teacher.mean(0)) + teacher.mean(0), teacher)) == pytest.approx(0, abs=1e-6)
    assert code_anchor(teacher[:0], teacher[:0]) == 0


def test_anchor_keeps_a_fine_tune_near_its_init_weights(real_frames):
    """A few aggressive steps from the shipped weights on 6 real frames: with ``anchor`` the codes of the clean frames
    stay nearer the shipped weights' codes than without (red when the term is dropped)."""
    from cae.weights import DEFAULT_WEIGHTS, load_checkpoint

    state = load_checkpoint(DEFAULT_WEIGHTS)
    x = training._to_batch(real_frames.images, torch.device("cpu"))

    def moved(anchor):
        model = ConvAutoencoder("standardise")
        model.load_state_dict(state["state_dict"])
        teacher = training._teacher(merge_conf(default_conf, {"anchor": 1.0, "init": "shipped"}), torch.device("cpu"))
        with torch.no_grad():
            before = teacher.forward_map(x).flatten(1)
        optim = torch.optim.Adam(model.parameters(), lr=1e-3)  # train.py's default
        conf = merge_conf(default_conf, {"far": 2, "neighbours": 0, "recon_share": 0.25, "anchor": anchor})
        for step in range(4):
            optim.zero_grad()
            _place_step(model, real_frames, np.arange(len(real_frames)), np.random.default_rng(step), conf,
                        torch.device("cpu"), np.zeros((0, 2), np.int64), teacher if anchor else None)
            optim.step()
        with torch.no_grad():
            return float(code_anchor(model.encoder.forward_map(x).flatten(1), before))

    free, anchored = moved(0.0), moved(default_conf["anchor"])
    assert anchored < 0.5 * free, (anchored, free)


def test_sensor_noise_is_as_coarse_as_its_grain():
    """``grain`` draws the views' noise on a coarser grid, as a sensor with fewer pixels than the network reads:
    neighbouring pixels share it (per network pixel, ``grain`` 1, they do not); empty in, empty out."""
    from cae.views import _sensor_noise, photometric

    only_noise = {"colour": 0.0, "grey": 0.0, "night": 0.0, "noise": 0.1, "low_res": 0.0, "blur": 0.0, "jpeg": 0.0,
                  "shade": 0.0}
    x = torch.full((8, 3, 64, 64), 0.5)

    def neighbour_corr(grain):
        n = photometric(x, np.random.default_rng(0), 0.0, {**only_noise, "grain": grain}) - x
        return float((n[..., 1:] * n[..., :-1]).mean() / (n * n).mean())

    assert abs(neighbour_corr(1.0)) < 0.05 and neighbour_corr(8.0) > 0.5
    fine = _sensor_noise(np.random.default_rng(0), x, 1.0)
    assert fine.shape == x.shape and 0.95 < float(fine.std()) < 1.05
    assert _sensor_noise(np.random.default_rng(0), x, 8.0).shape == x.shape
    assert _sensor_noise(np.random.default_rng(0), x[:0], 8.0).shape == (0, 3, 64, 64)


def test_sampling_follows_the_folder_order():
    folder, position = np.array([0, 0, 0, 0, 1, 1]), np.array([0, 1, 2, 3, 0, 1])
    rng = np.random.default_rng(0)
    for _ in range(20):
        p = neighbour_partners(folder, position, np.arange(6), 1, rng)
        assert (folder[p] == folder).all() and (np.abs(position[p] - position) <= 1).all()
    assert (neighbour_partners(folder, position, np.arange(6), 0, rng) == np.arange(6)).all()
    m = far_mask(folder, position, 2)
    assert m[0, 2] and not m[0, 1] and not m[0, 0] and m[0, 4]  # 2 apart: negative; 1 apart: left out


def test_sequence_order_per_folder(tmp_path):
    files = [tmp_path / "b" / "2.png", tmp_path / "a" / "1.png", tmp_path / "b" / "1.png"]
    folder, position = sequence_order(files)
    assert folder[0] == folder[2] != folder[1]
    assert position.tolist() == [1, 0, 0]


def test_views_keep_shape_range_and_seed(real_frames):
    conf = merge_conf(default_conf, {"views": {"night": 1.0, "low_res": 1.0, "jpeg": 1.0, "blur": 1.0}})
    x = training._to_batch(real_frames.images[:3], torch.device("cpu"))
    target, a = _view(x, np.random.default_rng(5), conf)
    _, b = _view(x, np.random.default_rng(5), conf)
    assert a.shape == target.shape == x.shape and torch.equal(a, b)  # one seed, one view
    assert 0 <= float(a.min()) and float(a.max()) <= 1 and float(a.mean()) < float(x.mean())  # all made dark
    empty = _view(x[:0], np.random.default_rng(0), conf)[1]
    assert empty.shape == (0, *x.shape[1:])
