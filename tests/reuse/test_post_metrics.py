"""Post-processing operator, PSNR/SSIM definitions, equivalent spp."""

import numpy as np
import pytest

from dpmhw.metrics import equivalent_spp, luma, masked_psnr, psnr, ssim
from dpmhw.postprocess import ProjectorResponse, postprocess, srgb_decode, srgb_encode, to_srgb8, tonemap


def test_to_srgb8_is_exposure_clip_srgb():
    rng = np.random.default_rng(0)
    x = rng.uniform(-0.5, 2.0, (8, 9, 3)).astype(np.float32)
    expected = np.round(255 * srgb_encode(np.clip(x * 0.7, 0, 1))).astype(np.uint8)
    got = to_srgb8(x, 0.7)
    assert np.abs(got.astype(int) - expected).max() <= 1 and got.dtype == np.uint8
    assert to_srgb8(np.full((1, 1, 3), 1.0, np.float32))[0, 0, 0] == 255
    assert to_srgb8(np.full((1, 1, 3), 0.0031308 * 0.5, np.float32))[0, 0, 0] == round(255 * 12.92 * 0.0031308 * 0.5)
    np.testing.assert_allclose(srgb_decode(srgb_encode(np.linspace(0, 1, 101))), np.linspace(0, 1, 101), atol=1e-12)


def test_nonfinite_radiance_is_refused():
    bad = np.zeros((2, 2, 3), np.float32)
    bad[1, 1, 2] = np.nan
    with pytest.raises(ValueError, match="NaN/Inf"):
        postprocess(bad)


def test_reinhard_maps_white_to_one_and_is_monotone():
    x = np.linspace(0, 10, 1001, dtype=np.float32)
    y = tonemap(x, "reinhard", white=4.0)
    assert y[0] == 0 and np.all(np.diff(y) >= 0) and y[400] == pytest.approx(1.0) and np.all(y <= 1)
    assert tonemap(np.float32(0.01), "reinhard") == pytest.approx(0.01, rel=0.02)  # linear near black
    with pytest.raises(ValueError, match="tonemap"):
        tonemap(x, "aces")


def test_projector_response_table_inverts_the_measured_curve(tmp_path):
    codes = np.arange(0, 256, 5.0)
    codes[-1] = 255
    table = tmp_path / "response.csv"
    table.write_text("code,linear\n" + "\n".join(f"{c:g},{(c / 255) ** 2.2:.9f}" for c in codes))
    resp = ProjectorResponse.from_csv(table)
    x = np.array([[[0.0, 0.18, 1.0], [0.5, 0.01, 0.9]]], np.float32)
    got = postprocess(x, response=resp).astype(float)
    np.testing.assert_allclose(got, 255 * x ** (1 / 2.2), atol=1.6)  # interpolation between table rows
    with pytest.raises(ValueError, match="increase"):
        ProjectorResponse([0, 10, 5], [0, 0.5, 1])


def test_psnr_definition():
    ref = np.full((4, 5, 3), 100, np.uint8)
    assert psnr(ref + 1, ref) == pytest.approx(20 * np.log10(255))
    img = ref.copy()
    img[0, 0, 0] = 110  # MSE = 100 / 60
    assert psnr(img, ref) == pytest.approx(10 * np.log10(255**2 / (100 / 60)))
    assert psnr(ref, ref) == float("inf")
    with pytest.raises(ValueError, match="uint8"):
        psnr(ref.astype(float), ref)


def test_masked_psnr_is_the_psnr_of_the_masked_pixels_and_nan_for_none():
    ref = np.zeros((4, 4, 3), np.uint8)
    img = ref.copy()
    img[0] = 10  # the error is all in row 0
    mask = np.zeros((4, 4), bool)
    mask[:2] = True
    assert masked_psnr(img, ref, mask) == pytest.approx(10 * np.log10(255.0**2 / 50.0))  # mse 100 over half the pixels
    assert masked_psnr(img, ref, ~mask) == float("inf")
    assert np.isnan(masked_psnr(img, ref, np.zeros((4, 4), bool)))


def test_ssim_is_wang_2004_on_luma():
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(1)
    ys, xs = np.mgrid[0:40, 0:50]
    ref = np.repeat((128 + 90 * np.sin(xs / 4.0) * np.cos(ys / 5.0))[..., None], 3, -1).astype(np.uint8)
    noisy = np.clip(ref + rng.normal(0, 25, ref.shape), 0, 255).astype(np.uint8)
    assert ssim(ref, ref) == pytest.approx(1.0)
    expected = structural_similarity(luma(noisy), luma(ref), gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=255.0)
    assert ssim(noisy, ref) == pytest.approx(expected)
    # not the default (uniform 7×7, sample covariance) variant
    assert abs(ssim(noisy, ref) - structural_similarity(luma(noisy), luma(ref), data_range=255.0)) > 1e-2
    assert luma(np.array([[[255, 255, 255]]], np.uint8))[0, 0] == pytest.approx(255 * (0.2989 + 0.5870 + 0.1140))


def test_equivalent_spp_interpolates_on_log_spp():
    spp = [1, 2, 4, 8, 16]
    curve = [20 + 10 * np.log10(n) for n in spp]  # MSE ∝ 1/spp
    eq, extrapolated = equivalent_spp(spp, curve, 20 + 10 * np.log10(9))
    assert eq == pytest.approx(9, rel=0.02) and not extrapolated
    eq, extrapolated = equivalent_spp(spp, curve, 20 + 10 * np.log10(39))
    assert eq == pytest.approx(39, rel=0.02) and extrapolated
    with pytest.raises(ValueError, match="rise"):
        equivalent_spp([1, 2, 4], [20, 19, 25], 21)


def test_noise_corrected_psnr_recovers_the_error_against_the_truth():
    """Synthetic, with a known truth: a smooth linear image T; the halves A, B have noise of
    variance 2σ_r² each (so R = (A + B)/2 has σ_r²), the image X noise σ_x², all independent, through
    the real post-processing. The raw PSNR against R is biased low by R's noise; the corrected
    one matches the PSNR against T."""
    from dpmhw.metrics import noise_corrected_psnr, psnr, reference_noise_mse
    from dpmhw.postprocess import postprocess

    rng = np.random.default_rng(5)
    H, W = 384, 512
    y, x = np.mgrid[0:H, 0:W]
    truth = (0.05 + 0.35 * (x / W) + 0.2 * (y / H))[..., None] * np.array([1.0, 0.9, 0.8])
    for sigma_x, sigma_r in ((0.004, 0.006), (0.01, 0.01), (0.003, 0.012)):
        a = truth + rng.normal(0, sigma_r * np.sqrt(2), truth.shape)
        b = truth + rng.normal(0, sigma_r * np.sqrt(2), truth.shape)
        img = truth + rng.normal(0, sigma_x, truth.shape)
        t8, a8, b8, x8 = (postprocess(v.astype(np.float32)) for v in (truth, a, b, img))
        r8 = postprocess(((a + b) / 2).astype(np.float32))
        true_db = psnr(x8, t8)
        raw_db = psnr(x8, r8)
        corrected_db = noise_corrected_psnr(x8, r8, a8, b8)
        assert raw_db < true_db - 1.0  # the reference's noise caps the plain PSNR
        # the corrected MSE is right to a few % of the reference's noise: within 0.25 dB while the
        # image's error is not far below that noise (the third case: 11 dB below, off by 0.5 dB)
        ref_noise = np.mean((r8.astype(float) - t8.astype(float)) ** 2)
        mse = lambda db: 255.0**2 / 10 ** (db / 10)  # noqa: E731
        assert abs(mse(corrected_db) - mse(true_db)) < 0.03 * ref_noise, (sigma_x, sigma_r, raw_db, corrected_db, true_db)
        if sigma_x >= sigma_r / 2:
            assert abs(corrected_db - true_db) < 0.25, (sigma_x, sigma_r, raw_db, corrected_db, true_db)
        # the estimate of the reference's own noise, against its actual MSE from the truth
        assert abs(reference_noise_mse(a8, b8) / ref_noise - 1.0) < 0.1
        mask = x > W // 2
        assert abs(noise_corrected_psnr(x8, r8, a8, b8, mask) - psnr(x8[mask], t8[mask])) < 0.3


def test_noise_corrected_psnr_is_capped_within_the_references_noise():
    from dpmhw.metrics import noise_corrected_psnr

    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (32, 32, 3), dtype=np.uint8)
    b = rng.integers(0, 256, (32, 32, 3), dtype=np.uint8)
    r = ((a.astype(int) + b) // 2).astype(np.uint8)
    assert noise_corrected_psnr(r, r, a, b, max_db=70.0) == pytest.approx(70.0)
    assert np.isnan(noise_corrected_psnr(r, r, a, b, np.zeros((32, 32), bool)))
