import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sqparts


def _numpy_gamma(rendered, hit, measured, figure, sigma, lam, num_bins):
    """Reference Γ in a few lines of numpy: half-width bins anchored at the first valid
    difference, best adjacent pair."""
    both = hit & figure & np.isfinite(measured)
    diff = (rendered - measured)[both]
    half = sigma / 2
    anchor = diff[0] if diff.size else 0.0
    edges = anchor + (np.arange(num_bins + 1) - num_bins // 2) * half
    counts, _ = np.histogram(diff, bins=edges)
    pairs = counts[:-1] + counts[1:]
    mu = float(pairs.max())
    # Commission: hit off the figure, unless a return lies in front of the window [lo, lo + σ).
    with np.errstate(invalid="ignore"):
        hidden = np.isfinite(measured) & (rendered - measured > edges[np.argmax(pairs)] + sigma)
    eps = float((hit & ~figure & ~hidden).sum())
    return mu - lam * eps


def test_gamma_matches_numpy_histogram():
    rng = np.random.default_rng(0)
    for trial in range(20):
        n = 300
        measured = rng.uniform(1, 2, n).astype(np.float32)
        measured[rng.random(n) < 0.2] = np.nan
        figure = np.isfinite(measured) & (rng.random(n) < 0.9)
        hit = rng.random(n) < 0.7
        offset = rng.uniform(-0.2, 0.2)
        rendered = np.where(rng.random(n) < 0.6, measured + offset + rng.normal(0, 0.003, n), rng.uniform(0.5, 2.5, n))
        rendered = np.nan_to_num(rendered).astype(np.float32)
        ours = sqparts.gamma(
            jnp.asarray(rendered),
            jnp.asarray(hit),
            jnp.asarray(measured),
            jnp.asarray(figure),
            sigma=0.02,
            commission_weight=4.0,
            num_bins=200,
        )
        ref = _numpy_gamma(rendered, hit, measured, figure, 0.02, 4.0, 200)
        assert float(ours) == pytest.approx(ref), trial


def test_peak_straddling_a_bin_edge_is_counted_whole():
    # 1063 pixels all within 0.3σ of each other, centred on what would be a fixed σ-bin edge.
    sigma = 4.0
    rng = np.random.default_rng(1)
    diff = 8.0 + rng.uniform(-0.3, 0.3, 1063) * sigma / 2
    measured = np.full(1063, 100.0, np.float32)
    rendered = (measured + diff).astype(np.float32)
    ones = np.ones(1063, bool)
    fixed, _ = np.histogram(diff, bins=np.arange(0, 20, sigma))  # fixed σ bins split the peak
    assert fixed.max() < 1063
    mu, eps, p, explained = sqparts.gamma_terms(
        jnp.asarray(rendered), jnp.asarray(ones), jnp.asarray(measured), jnp.asarray(ones), sigma=sigma, num_bins=64
    )
    assert float(mu) == 1063 and float(eps) == 0 and bool(np.all(explained))
    assert abs(float(p) - 8.0) <= sigma / 2


def test_encoding_bits():
    enc = sqparts.Encoding(sigma=4.0, quantum=1.0, depth_range=256.0)
    assert enc.pixel_bits == 8 and enc.noise_bits == 2 and enc.part_bits == 112
    assert enc.bits_saved(100.0) == pytest.approx(-112 + 6 * 100)
    q = np.round(np.random.default_rng(0).uniform(0, 1, 1000) * 32) / 32  # 5-bit data
    enc = sqparts.encoding_for(q)
    assert enc.quantum == pytest.approx(1 / 32) and enc.sigma == pytest.approx(4 / 32)
    assert enc.part_bits == pytest.approx(14 * 0.5 * np.log2(1000))  # ½ log2 N bits per parameter
    with pytest.raises(ValueError, match=r"sigma: got .*, expected a finite number > 0"):
        sqparts.Encoding(sigma=-1.0, quantum=1.0, depth_range=2.0)
    with pytest.raises(ValueError, match=r"depth: got \d+ valid pixels, expected at least 2"):
        sqparts.encoding_for(np.array([np.nan, 1.0]))
    # A figure shallower than σ (a plate facing the camera: σ from its pixel footprint):
    # a raw pixel costs at least κ1 + ½, so an explained pixel still saves ½ bit.
    shallow = sqparts.Encoding(sigma=0.015, quantum=0.003 / 64, depth_range=0.003)
    assert shallow.noise_bits == pytest.approx(np.log2(320))
    assert shallow.pixel_bits == pytest.approx(np.log2(320) + 0.5)
    assert shallow.saved_per_pixel == pytest.approx(0.5)


def test_a_plate_facing_the_camera_is_one_part_that_explains_it():
    # Its depth varies by under a millimetre, far below σ (half a pixel footprint, 15
    # mm): a part explaining a pixel cost more bits than the raw pixel, and recovery
    # returned one part that explained none of it.
    cam = sqparts.PinholeCamera(32, 32, 100.0, 100.0, 15.5, 15.5)
    plate = sqparts.Part(size=[0.2, 0.2, 0.02], squareness=[0.1, 0.1], position=[0.0, 0.0, 3.0])
    depth = np.asarray(sqparts.render_range_image(plate, cam))
    assert np.nanmax(depth) - np.nanmin(depth) < 1e-3
    rec = sqparts.recover(depth, cam)
    assert len(rec.parts) == 1 and rec.fraction_explained > 0.95
    np.testing.assert_allclose(np.sort(np.asarray(rec.parts.size)[0])[1:], [0.2, 0.2], rtol=0.15)  # its face


CAM = sqparts.OrthographicCamera(48, 48, 0.01, 23.5, 23.5)
PIN = sqparts.PinholeCamera(48, 48, 70.0, 70.0, 23.5, 23.5)


def _gamma_of(part, depth, camera, enc, figure=None):
    figure = np.isfinite(depth) if figure is None else figure
    o, d = camera.rays()
    from sqparts._render import cast_part

    @jax.jit
    def run(part, depth, figure):
        t, hit = cast_part(part, o, d)
        return sqparts.gamma(
            t, hit, depth, figure, sigma=enc.sigma, commission_weight=enc.commission_weight, num_bins=256
        )

    return float(run(part, jnp.asarray(depth), jnp.asarray(figure)))


def test_moving_a_part_in_depth_leaves_gamma_unchanged():
    part = sqparts.Part(
        size=[0.1, 0.08, 0.15], squareness=[0.5, 1.0], position=[0.01, 0, 1.0], orientation=[0.3, 0.5, 0.1]
    )
    depth = np.asarray(sqparts.render_range_image(part, CAM))
    enc = sqparts.encoding_for(depth)
    base = _gamma_of(part, depth, CAM, enc)
    assert base == np.isfinite(depth).sum()
    for dz in (-0.3, 0.07, 0.5):
        moved = sqparts.Part.from_vector(part.to_vector().at[2].add(dz))
        assert _gamma_of(moved, depth, CAM, enc) == base


def test_half_hidden_part_still_scores_its_visible_pixels():
    hidden = sqparts.Part(size=[0.12, 0.12, 0.12], position=[0.0, 0.0, 1.0])
    occluder = sqparts.Part(size=[0.08, 0.2, 0.05], squareness=[0.2, 0.2], position=[0.06, 0.0, 0.8])
    depth, labels = sqparts.render_range_image(sqparts.stack_parts([hidden, occluder]), CAM, return_labels=True)
    depth, labels = np.asarray(depth), np.asarray(labels)
    visible = int((labels == 0).sum())
    alone = int(np.isfinite(np.asarray(sqparts.render_range_image(hidden, CAM))).sum())
    assert visible < 0.75 * alone  # really half hidden
    enc = sqparts.encoding_for(depth)
    g = _gamma_of(hidden, depth, CAM, enc)
    assert visible - 3 <= g <= visible  # occluded pixels are neither explained nor commission


def test_commission_spares_pixels_another_figure_hides_but_not_a_surface_behind():
    part = sqparts.Part(size=[0.12, 0.12, 0.12], position=[0.0, 0.0, 1.0])
    occluder = sqparts.Part(size=[0.08, 0.2, 0.05], squareness=[0.2, 0.2], position=[0.06, 0.0, 0.8])
    wall = sqparts.Part(size=[0.5, 0.5, 0.02], squareness=[0.2, 0.2], position=[0.0, 0.0, 1.4])
    depth, labels = (
        np.asarray(x)
        for x in sqparts.render_range_image(sqparts.stack_parts([part, occluder, wall]), CAM, return_labels=True)
    )
    figure = labels == 0  # the part's own figure: the occluder and the wall are other figures
    enc = sqparts.encoding_for(depth[figure])
    visible = int(figure.sum())
    alone = np.isfinite(np.asarray(sqparts.render_range_image(part, CAM)))
    assert (alone & (labels == 1)).sum() > 0.25 * alone.sum()  # a quarter hidden by the occluder
    # Hidden by a figure in front: neither explained nor commission.
    assert visible - 3 <= _gamma_of(part, depth, CAM, enc, figure) <= visible
    # A swollen part covers wall pixels behind it: every one of those is commission.
    big = sqparts.Part(size=[0.15, 0.15, 0.12], position=[0.0, 0.0, 1.0])
    big_hit = np.isfinite(np.asarray(sqparts.render_range_image(big, CAM)))
    ring = int((big_hit & (labels == 2)).sum())
    assert ring > 50
    g = _gamma_of(big, depth, CAM, enc, figure)
    assert g <= visible - enc.commission_weight * ring + 3


def test_smooth_gamma_approximates_gamma_and_has_gradients():
    part = sqparts.Part(
        size=[0.1, 0.08, 0.15], squareness=[0.5, 1.0], position=[0.01, 0, 1.0], orientation=[0.3, 0.5, 0.1]
    )
    depth = jnp.asarray(sqparts.render_range_image(part, PIN))
    fig = jnp.isfinite(depth)
    o, d = PIN.rays()
    from sqparts._render import cast_part

    def sg(v):
        t, hit = cast_part(sqparts.Part.from_vector(v), o, d)
        return sqparts.smooth_gamma(t, hit, depth, fig, 0.0, sigma=0.02, commission_weight=4.0)

    v = part.to_vector()
    assert float(sg(v)) == pytest.approx(float(fig.sum()), rel=1e-3)
    g = jax.grad(sg)(v.at[2].add(0.008))
    assert np.all(np.isfinite(g)) and float(g[2]) < 0  # pulls the part back toward the data
