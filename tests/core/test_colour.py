"""One sRGB codec (core.colour): the torch curve, the same curve on numpy arrays, and BT.709 through
colour-science; the values are colour-science's to float32 precision."""

import colour
import numpy as np
import pytest
import torch

from mono_hdr_plugin.core.colour import decode_curve, encode_curve, srgb_decode, srgb_encode


@pytest.mark.parametrize("curve,name", [("srgb", "sRGB"), ("bt709", "ITU-R BT.709")])
def test_numpy_curves_are_colour_sciences(curve, name):
    linear = np.concatenate([np.linspace(0, 1.5, 4001), np.random.default_rng(0).random(10_000) ** 4])
    np.testing.assert_allclose(
        encode_curve(linear, curve), colour.cctf_encoding(linear, function=name), rtol=1e-12, atol=1e-15
    )
    encoded = np.linspace(0, 1, 4001)
    np.testing.assert_allclose(
        decode_curve(encoded, curve), colour.cctf_decoding(encoded, function=name), rtol=1e-9, atol=1e-15
    )
    assert encode_curve(linear, curve).dtype == np.float64


def test_numpy_srgb_is_the_torch_curve_on_float32_data():
    linear = np.random.default_rng(1).random(10_000).astype(np.float32)
    expected = srgb_encode(torch.from_numpy(linear).double()).float().numpy()
    np.testing.assert_array_equal(encode_curve(linear, "srgb").astype(np.float32), expected)
    np.testing.assert_array_equal(
        decode_curve(linear, "srgb").astype(np.float32), srgb_decode(torch.from_numpy(linear).double()).float().numpy()
    )
