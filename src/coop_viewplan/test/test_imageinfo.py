"""App. C measures on hand-checkable images."""
from __future__ import annotations

import numpy as np
import pytest

from coop_viewplan.imageinfo import (
    compression_ratio,
    huffman_length,
    information_bits,
    residual,
    shannon_bits,
)


def test_entropy_and_huffman_on_known_distribution():
    s = np.array([0] * 8 + [1] * 4 + [2] * 2 + [3] * 2)   # p = 1/2, 1/4, 1/8, 1/8
    assert shannon_bits(s) == pytest.approx(1.75)
    assert huffman_length(s) == pytest.approx(1.75)        # dyadic: Huffman is optimal
    s2 = np.array([0, 0, 1])
    assert huffman_length(s2) == pytest.approx(1.0)
    assert shannon_bits(s2) < 1.0


def test_predictor_5_constant_residual_on_bilinear_surface():
    u, v = np.mgrid[0:16, 0:16]
    img = (u * v).astype(np.uint8)        # W + N - NW = uv - 1: residual 1 everywhere inside
    r = residual(img, 5)
    assert np.all(r[1:, 1:] == 1)
    assert np.array_equal(residual(img, 2)[1:, 1:], u[1:, 1:])
    assert compression_ratio(img, 5) > compression_ratio(img, 2) > 1.0
    assert compression_ratio(img, 1) == 1.0


def test_noise_does_not_compress():
    img = np.random.default_rng(0).integers(0, 256, (128, 128)).astype(np.uint8)
    for m in range(2, 10):
        assert compression_ratio(img, m) < 1.0
    assert compression_ratio(img, 10) == pytest.approx(1.0, abs=0.01)
    assert information_bits(img) > 7.5 * img.size


def test_table_c_1_cli_reduced(tmp_path, capsys):
    import json

    from coop_viewplan import table_c_1
    out = tmp_path / 'c.json'
    assert table_c_1.main(['--images', '3', '--noise', '2', '--json', str(out)]) == 0
    data = json.loads(out.read_text())
    scenes = data['results']['scenes']
    # rendered scenes compress with predictor 5 at 256^2; pure noise does not
    assert scenes['5'][-1][0] > 1.0
    assert data['results']['noise']['5'][-1][0] < 1.0
    printed = capsys.readouterr().out
    assert 'best predictor' in printed
    # the results page's table is made from the JSON by the function that printed it
    assert printed.startswith(table_c_1.format_json(data) + '\n')
