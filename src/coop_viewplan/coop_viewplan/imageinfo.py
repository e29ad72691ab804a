"""Image information measure of App. C: Shannon entropy of an 8-bit image before and after the
lossless-JPEG predictors (methods 2-9 of Table C-1) and Huffman coding (method 10).

Compression ratio CR = H(image) / H(residual) in bits per pixel (Eq. 3-12 on the histogram of
Eq. 3-13); for Huffman coding the denominator is the average code length. Predictor 5
(I - (W + N - NW)) is the one the thesis carries into the planner.
"""
from __future__ import annotations

import heapq

import numpy as np


def shannon_bits(symbols: np.ndarray) -> float:
    """Eq. 3-12 over the histogram of Eq. 3-13 (bits per symbol)."""
    s = np.asarray(symbols).ravel()
    if s.size == 0:
        raise ValueError('empty image')
    _, counts = np.unique(s, return_counts=True)
    q = counts / s.size
    return float(-(q * np.log2(q)).sum())


def prediction(i: np.ndarray, method: int) -> np.ndarray:
    """Table C-1 predictor of method 2..9 for every pixel with all three neighbours, over the
    last two axes (..., rows u, columns v) of an integer array: W = I(u, v-1), N = I(u-1, v),
    NW = I(u-1, v-1). Returns the prediction of i[..., 1:, 1:]."""
    if method not in range(2, 10):
        raise ValueError(f'method must be 2..9 for a predictor, got {method}')
    w, n, nw = i[..., 1:, :-1], i[..., :-1, 1:], i[..., :-1, :-1]
    return {2: lambda: w, 3: lambda: n, 4: lambda: nw, 5: lambda: w + n - nw,
            6: lambda: w + (n - nw) // 2, 7: lambda: n + (w - nw) // 2,
            8: lambda: (n + w) // 2, 9: lambda: (n + nw + w) // 3}[method]()


def residual(image: np.ndarray, method: int) -> np.ndarray:
    """Prediction residual of Table C-1 method 2..9 (method 1: the image). u indexes rows,
    v columns (see `prediction`). The first row and column, which lack neighbours, keep their
    values (as lossless JPEG does)."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError('image must be 2-D (mono)')
    i = img.astype(np.int64)
    if method == 1:
        return i
    if method not in range(2, 10):
        raise ValueError(f'method must be 1..9 for a residual, got {method}')
    out = i.copy()
    out[1:, 1:] = i[1:, 1:] - prediction(i, method)
    return out


def huffman_length(symbols: np.ndarray) -> float:
    """Average Huffman code length (bits per symbol), built as in §C.3."""
    _, counts = np.unique(np.asarray(symbols).ravel(), return_counts=True)
    if len(counts) == 1:
        return 1.0
    heap = [(int(c), k, 0) for k, c in enumerate(counts)]
    heapq.heapify(heap)
    total_bits = 0
    k = len(heap)
    while len(heap) > 1:
        a, _, _ = heapq.heappop(heap)
        b, _, _ = heapq.heappop(heap)
        # every symbol under the new parent gains one bit: add the parent's weight
        total_bits += a + b
        heapq.heappush(heap, (a + b, k, 0))
        k += 1
    return total_bits / counts.sum()


def compression_ratio(image: np.ndarray, method: int) -> float:
    """CR of Table C-1 for method 1..10."""
    before = shannon_bits(np.asarray(image))
    if before == 0:
        return 1.0
    if method == 10:
        return before / huffman_length(image)
    after = shannon_bits(residual(image, method))
    return before / after if after > 0 else float('inf')


def information_bits(image: np.ndarray) -> float:
    """Scene information used by the planner: total bits after predictor 5."""
    return shannon_bits(residual(image, 5)) * np.asarray(image).size
