"""Image similarity for 3D-2D registration: gradient orientation (GO), NCC and gradient NCC.

All metrics compare one fixed image (the radiograph) ``(H, W)`` with a batch of moving images
(DRRs of candidate poses) ``(..., H, W)`` and return one score per moving image, larger is better.

Gradient orientation (Han et al. 2020, equation 10, after De Silva et al. 2016)::

    GO(I1, I2) = 1 / max(N, N_LB) * sum_{i in Omega} (2 - ln(|psi_i| + 1)) / 2

where ``Omega`` are the pixels whose gradient magnitude exceeds the median of its own image in
*both* images, ``N = |Omega|``, ``N_LB`` half the number of pixels, and ``psi_i`` the angle
(radians, in [0, pi]) between the two gradient vectors. Thresholding at each image's median makes GO
invariant to positive intensity scaling and offsets and blind to weak (soft-tissue) gradients; the
lower bound ``N_LB`` stops a candidate from scoring well by overlapping only a few edges.
Gradients are Sobel derivatives.
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "GradientNCC",
    "GradientOrientation",
    "gradient_ncc",
    "gradient_ncc_gradients",
    "gradient_orientation",
    "ncc",
    "sobel_gradients",
]


def _check_pair(fixed: ArrayLike, moving: ArrayLike) -> tuple[NDArray, NDArray]:
    f = np.asarray(fixed, dtype=np.float64)
    m = np.asarray(moving, dtype=np.float64)
    if f.ndim != 2:
        raise ValueError(f"fixed image must be 2D (H, W), got shape {f.shape}")
    if m.ndim < 2 or m.shape[-2:] != f.shape:
        raise ValueError(
            f"moving images must have shape (..., {f.shape[0]}, {f.shape[1]}), got {m.shape}"
        )
    if min(f.shape) < 3:
        raise ValueError(f"images must be at least 3 x 3 pixels, got {f.shape}")
    if not (np.all(np.isfinite(f)) and np.all(np.isfinite(m))):
        raise ValueError("images contain NaN or infinity")
    return f, m


def sobel_gradients(images: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Sobel derivatives along columns (x) and rows (y) of ``(..., H, W)`` images (edge padding).

    Only the last two axes are filtered, so a batch of images is differentiated independently.
    """
    a = np.asarray(images, dtype=np.float64)
    p = np.pad(a, [(0, 0)] * (a.ndim - 2) + [(1, 1), (1, 1)], mode="edge")
    # Smooth across, differentiate along: [1, 2, 1] x [-1, 0, 1].
    sx = p[..., :, 2:] - p[..., :, :-2]  # (..., H+2, W)
    gx = (sx[..., :-2, :] + 2 * sx[..., 1:-1, :] + sx[..., 2:, :]) / 8.0
    sy = p[..., 2:, :] - p[..., :-2, :]  # (..., H, W+2)
    gy = (sy[..., :, :-2] + 2 * sy[..., :, 1:-1] + sy[..., :, 2:]) / 8.0
    return gx, gy


def gradient_orientation(fixed: ArrayLike, moving: ArrayLike) -> NDArray[np.float64]:
    """GO of equation 10 between a fixed image and a batch of moving images.

    Parameters
    ----------
    fixed : (H, W) float
        The radiograph.
    moving : (..., H, W) float
        DRRs.

    Returns
    -------
    (...) float64
        In [0, 1]; about 1 for identical images.

    Raises
    ------
    ValueError
        Shape mismatch, images smaller than 3 x 3, or NaN/inf.
    """
    f, m = _check_pair(fixed, moving)
    fx, fy = sobel_gradients(f)
    mx, my = sobel_gradients(m)
    fmag = np.hypot(fx, fy)
    mmag = np.hypot(mx, my)
    t1 = np.median(fmag)
    t2 = np.median(mmag.reshape(*m.shape[:-2], -1), axis=-1)[..., None, None]
    omega = (fmag > t1) & (mmag > t2)
    cos = (fx * mx + fy * my) / np.maximum(fmag * mmag, 1e-300)
    psi = np.arccos(np.clip(cos, -1.0, 1.0))
    weight = np.where(omega, (2.0 - np.log(psi + 1.0)) / 2.0, 0.0)
    n = omega.sum(axis=(-2, -1))
    n_lb = 0.5 * f.size
    return weight.sum(axis=(-2, -1)) / np.maximum(n, n_lb)


def ncc(fixed: ArrayLike, moving: ArrayLike) -> NDArray[np.float64]:
    """Normalised cross-correlation (Pearson) over all pixels, ``(...)``; 0 for flat images."""
    f, m = _check_pair(fixed, moving)
    fz = f - f.mean()
    mz = m - m.mean(axis=(-2, -1), keepdims=True)
    num = np.sum(fz * mz, axis=(-2, -1))
    den = np.sqrt(np.sum(fz**2) * np.sum(mz**2, axis=(-2, -1)))
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)


def gradient_ncc(fixed: ArrayLike, moving: ArrayLike) -> NDArray[np.float64]:
    """Mean of the NCCs of the x and y Sobel gradients (Penney et al. 1998), ``(...)``."""
    f, m = _check_pair(fixed, moving)
    fx, fy = sobel_gradients(f)
    mx, my = sobel_gradients(m)
    return 0.5 * (ncc(fx, mx) + ncc(fy, my))


def _moving_batch(
    moving: ArrayLike, shape: tuple[int, int], *, strided: bool = False
) -> tuple[NDArray[np.float32], tuple]:
    """``(..., H, W)`` images as a float32 ``(n, H, W)`` batch, and the leading shape: C-contiguous,
    or (``strided``) any batch of float32 images whose rows are contiguous as it is, such as one
    view of a ``(B, K, H, W)`` DRR stack (copying every candidate's DRR cost a fifth of scoring it
    with GO). The caller checks that the images are finite."""
    m = np.asarray(moving)
    if m.ndim < 2 or m.shape[-2:] != shape:
        raise ValueError(
            f"moving images must have shape (..., {shape[0]}, {shape[1]}), got {m.shape}"
        )
    rows = m.ndim == 3 and m.dtype == np.float32 and m.strides[1:] == (4 * shape[1], 4)
    if strided and rows:
        return m, m.shape[:-2]
    return np.ascontiguousarray(m.reshape(-1, *shape), dtype=np.float32), m.shape[:-2]


def _finite(values: NDArray) -> NDArray:
    """``values``, or the error when one is not finite (the images held a NaN or an infinity)."""
    if not np.all(np.isfinite(values)):
        raise ValueError("images contain NaN or infinity")
    return values


class GradientOrientation:
    """GO against one fixed image, fast for many moving images (numba, parallel over images).

    Equation 10 like :func:`gradient_orientation` (same Sobel gradients, median thresholds and
    ``N_LB``); the fixed image's gradients and threshold are computed once, and the per-pixel
    weight comes from a fine table (relative difference < 1e-5 on whole images).

    Parameters
    ----------
    fixed : (H, W) float
    """

    def __init__(self, fixed: ArrayLike) -> None:
        f = np.asarray(fixed, dtype=np.float64)
        _check_pair(f, f)
        fx, fy = sobel_gradients(f)
        mag = np.hypot(fx, fy)
        self.shape = f.shape
        self._fx = np.ascontiguousarray(fx)
        self._fy = np.ascontiguousarray(fy)
        self._mask = np.ascontiguousarray(mag > np.median(mag))
        self._fmag = np.ascontiguousarray(mag)

    def __call__(self, moving: ArrayLike) -> NDArray[np.float64]:
        """GO of each image in ``moving`` ``(..., H, W)``; returns ``(...)``."""
        flat, lead = _moving_batch(moving, self.shape, strided=True)  # the kernel checks it
        out = np.empty(len(flat))
        import numba

        _compile_go()(self._fx, self._fy, self._fmag, self._mask, flat, _LUT,
                      numba.get_num_threads(), out)  # fmt: skip
        return _finite(out).reshape(lead)


# GO weight (2 - ln(psi + 1)) / 2 tabulated in s = sin(psi / 2) on [0, 1]; linear interpolation
# error < 2e-6 except within 1e-4 of s = 1 (opposite gradients), where it is < 1e-3.
_S = np.linspace(0.0, 1.0, 16385)
_LUT = (2.0 - np.log(2.0 * np.arcsin(_S) + 1.0)) / 2.0


@functools.cache  # compile once per process, on first use
def _compile_go():  # pragma: no cover - compiled code
    import numba as nb

    @nb.njit(parallel=True, cache=True)
    def kernel(fx, fy, fmag, mask, moving, lut, threads, out):
        nlut = lut.shape[0]
        n, H, W = moving.shape
        n_lb = 0.5 * H * W
        half = (H * W) // 2
        threads = max(1, min(threads, n))
        for t in nb.prange(threads):  # one scratch set per thread, its images in turn
            gx = np.empty((H, W))
            gy = np.empty((H, W))
            mag = np.empty(H * W)
            buf = np.empty(H * W)
            hist = np.empty(4096, dtype=np.int64)
            for b in range(t, n, threads):
                img = moving[b]
                vmax = 0.0
                check = 0.0  # not finite if a pixel is not (each is in a neighbour's stencil)
                for r in range(H):
                    r0 = r - 1 if r > 0 else 0
                    r2 = r + 1 if r < H - 1 else H - 1
                    for c in range(W):
                        c0 = c - 1 if c > 0 else 0
                        c2 = c + 1 if c < W - 1 else W - 1
                        a = np.float64(img[r0, c2]) - img[r0, c0]
                        bb = np.float64(img[r, c2]) - img[r, c0]
                        cc = np.float64(img[r2, c2]) - img[r2, c0]
                        x = (a + 2.0 * bb + cc) / 8.0
                        a = np.float64(img[r2, c0]) - img[r0, c0]
                        bb = np.float64(img[r2, c]) - img[r0, c]
                        cc = np.float64(img[r2, c2]) - img[r0, c2]
                        y = (a + 2.0 * bb + cc) / 8.0
                        gx[r, c] = x
                        gy[r, c] = y
                        m = np.sqrt(x * x + y * y)
                        mag[r * W + c] = m
                        vmax = max(vmax, m)
                        check += x + y
                if not np.isfinite(check):
                    out[b] = np.nan
                    continue
                # the median as np.median takes it: the order statistic(s) found by a histogram
                # of the magnitudes, then a partition of one bin's values (exact; a partition of
                # the whole image was 2x slower). Written out: numba does not cache a kernel
                # calling a jitted closure.
                scale = (4095.0 / vmax) if vmax > 0 else 0.0
                hist[:] = 0
                for i in range(H * W):
                    hist[int(mag[i] * scale)] += 1
                t_med = 0.0
                ks = (half, half - 1) if (H * W) % 2 == 0 else (half, half)
                for k in ks:
                    below, j = 0, 0
                    while below + hist[j] <= k:
                        below += hist[j]
                        j += 1
                    m = 0
                    for i in range(H * W):
                        if int(mag[i] * scale) == j:
                            buf[m] = mag[i]
                            m += 1
                    t_med += 0.5 * np.partition(buf[:m], k - below)[k - below]
                total = 0.0
                count = 0
                for r in range(H):
                    for c in range(W):
                        mm = mag[r * W + c]
                        if mask[r, c] and mm > t_med:
                            count += 1
                            cos = (fx[r, c] * gx[r, c] + fy[r, c] * gy[r, c]) / max(
                                fmag[r, c] * mm, 1e-300
                            )
                            # weight (2 - ln(psi + 1)) / 2 from a table in s = sin(psi / 2),
                            # which is smooth where psi is small (the aligned, decisive pixels)
                            x = np.sqrt(max(0.0, 0.5 * (1.0 - cos))) * (nlut - 1)
                            i = min(int(x), nlut - 2)
                            f = x - i
                            total += (1.0 - f) * lut[i] + f * lut[i + 1]
                out[b] = total / max(count, n_lb)

    return kernel


class GradientNCC:
    """Gradient NCC (:func:`gradient_ncc`) against one fixed image, fast for many moving images.

    The fixed image's zero-mean, unit-norm gradients ``f`` are computed once; each moving image
    is differentiated and correlated in one pass (numba, parallel over images) as
    ``sum(g f) / sqrt(sum(g^2) - n mean(g)^2)`` per gradient component, with no temporaries.

    Parameters
    ----------
    fixed : (H, W) float
    """

    def __init__(self, fixed: ArrayLike) -> None:
        f = np.asarray(fixed, dtype=np.float64)
        _check_pair(f, f)
        self.shape = f.shape
        g = []
        for d in sobel_gradients(f):
            z = d - d.mean()
            n = np.sqrt(np.sum(z * z))
            g.append(np.ascontiguousarray(z / n if n > 0 else z))
        self._fx, self._fy = g

    def __call__(self, moving: ArrayLike) -> NDArray[np.float64]:
        """Gradient NCC of each image in ``moving`` ``(..., H, W)``; returns ``(...)``."""
        # contiguous: the kernel's vectorised sums are 2x slower on strided rows; checked here, as
        # fastmath may drop a NaN
        flat, lead = _moving_batch(moving, self.shape)
        _finite(flat)
        out = np.empty(len(flat))
        _compile_gncc()(self._fx, self._fy, flat, out)
        return out.reshape(lead)

    def value_and_gradient(self, moving: ArrayLike) -> tuple[float, NDArray[np.float64]]:
        """Gradient NCC of one image ``(H, W)`` and its gradient with respect to every pixel
        (:func:`gradient_ncc_gradients`)."""
        values, grads = gradient_ncc_gradients([self], np.asarray(moving)[None])
        return float(values[0]), grads[0]


def gradient_ncc_gradients(
    metrics: list[GradientNCC] | tuple, images: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Gradient NCC of ``images[k]`` against ``metrics[k]``'s fixed image, and its gradient with
    respect to every pixel; the K images in parallel.

    With ``g = Dx I`` (Sobel), ``A = sum g f`` and ``V = sum (g - mean g)^2``, each component is
    ``A / sqrt(V)``, whose derivative is ``f / sqrt(V) - A (g - mean g) / V^1.5``, carried back
    through the Sobel stencil (its exact transpose, edge clamping included).

    Parameters
    ----------
    metrics : K GradientNCC
    images : (K, H, W) float

    Returns
    -------
    values : (K,) float64
    gradients : (K, H, W) float64
    """
    imgs = np.ascontiguousarray(images, dtype=np.float64)
    if imgs.ndim != 3 or len(imgs) != len(metrics):
        raise ValueError(f"need one (H, W) image per metric ({len(metrics)}), got {imgs.shape}")
    if any(m.shape != imgs.shape[1:] for m in metrics):
        raise ValueError(f"images of shape {imgs.shape[1:]} do not match the fixed images")
    fx, fy = _fixed_gradients(tuple(metrics))
    grads = np.zeros(imgs.shape)
    values = np.zeros(len(imgs))
    _compile_gncc_grad()(fx, fy, imgs, grads, values)
    return values, grads


# The Sobel stencil is written out in both kernels on purpose: a shared jitted helper captured
# from a closure stops numba caching the kernels (GO then recompiles for 10 s in every process).
@functools.cache  # compile once per process, on first use
def _compile_gncc():  # pragma: no cover - compiled code
    import numba as nb

    @nb.njit(parallel=True, cache=True, fastmath=True)  # fastmath: vectorised sums (1e-14)
    def kernel(fx, fy, moving, out):
        n, H, W = moving.shape
        npix = H * W
        for b in nb.prange(n):
            img = moving[b]
            sx = 0.0
            sy = 0.0
            sxx = 0.0
            syy = 0.0
            sxf = 0.0
            syf = 0.0
            for r in range(H):
                up = img[r - 1 if r > 0 else 0]
                mid = img[r]
                dn = img[r + 1 if r < H - 1 else H - 1]
                frx = fx[r]
                fry = fy[r]
                for c in range(W):
                    c0 = c - 1 if c > 0 else 0
                    c2 = c + 1 if c < W - 1 else W - 1
                    gx = (np.float64(up[c2]) - up[c0] + 2.0 * (np.float64(mid[c2]) - mid[c0])
                          + np.float64(dn[c2]) - dn[c0]) / 8.0  # fmt: skip
                    gy = (np.float64(dn[c0]) - up[c0] + 2.0 * (np.float64(dn[c]) - up[c])
                          + np.float64(dn[c2]) - up[c2]) / 8.0  # fmt: skip
                    sx += gx
                    sy += gy
                    sxx += gx * gx
                    syy += gy * gy
                    sxf += gx * frx[c]
                    syf += gy * fry[c]
            total = 0.0
            vx = sxx - sx * sx / npix  # sum of squared deviations (0 for a flat image)
            vy = syy - sy * sy / npix
            if vx > 1e-12 * sxx and vx > 0.0:
                total += sxf / np.sqrt(vx)
            if vy > 1e-12 * syy and vy > 0.0:
                total += syf / np.sqrt(vy)
            out[b] = 0.5 * total

    return kernel


@functools.lru_cache(maxsize=8)  # a refinement asks thousands of times for the same views
def _fixed_gradients(metrics: tuple[GradientNCC, ...]) -> tuple[NDArray, NDArray]:
    return np.stack([m._fx for m in metrics]), np.stack([m._fy for m in metrics])


@functools.cache  # compile once per process, on first use
def _compile_gncc_grad():  # pragma: no cover - compiled code
    import numba as nb

    @nb.njit(parallel=True, cache=True, error_model="numpy")
    def kernel(fxs, fys, imgs, grads, values):
        K, H, W = imgs.shape
        for k in nb.prange(K):
            img, fx, fy, grad = imgs[k], fxs[k], fys[k], grads[k]
            gx = np.empty((H, W))
            gy = np.empty((H, W))
            for r in range(H):
                r0 = r - 1 if r > 0 else 0
                r2 = r + 1 if r < H - 1 else H - 1
                for c in range(W):
                    c0 = c - 1 if c > 0 else 0
                    c2 = c + 1 if c < W - 1 else W - 1
                    gx[r, c] = (img[r0, c2] - img[r0, c0] + 2.0 * (img[r, c2] - img[r, c0])
                                + img[r2, c2] - img[r2, c0]) / 8.0  # fmt: skip
                    gy[r, c] = (img[r2, c0] - img[r0, c0] + 2.0 * (img[r2, c] - img[r0, c])
                                + img[r2, c2] - img[r0, c2]) / 8.0  # fmt: skip
            mx, my = gx.mean(), gy.mean()
            ax, ay = np.sum(gx * fx), np.sum(gy * fy)
            vx, vy = np.sum((gx - mx) ** 2), np.sum((gy - my) ** 2)
            value = 0.0
            sx = sy = cx = cy = 0.0  # d/dg = s f - c (g - mean)
            if vx > 1e-12 * np.sum(gx * gx) and vx > 0.0:
                value += 0.5 * ax / np.sqrt(vx)
                sx, cx = 0.5 / np.sqrt(vx), 0.5 * ax / vx**1.5
            if vy > 1e-12 * np.sum(gy * gy) and vy > 0.0:
                value += 0.5 * ay / np.sqrt(vy)
                sy, cy = 0.5 / np.sqrt(vy), 0.5 * ay / vy**1.5
            values[k] = value
            for r in range(H):  # the transpose of the stencil above
                r0 = r - 1 if r > 0 else 0
                r2 = r + 1 if r < H - 1 else H - 1
                for c in range(W):
                    c0 = c - 1 if c > 0 else 0
                    c2 = c + 1 if c < W - 1 else W - 1
                    a = (sx * fx[r, c] - cx * (gx[r, c] - mx)) / 8.0
                    grad[r0, c2] += a
                    grad[r0, c0] -= a
                    grad[r, c2] += 2.0 * a
                    grad[r, c0] -= 2.0 * a
                    grad[r2, c2] += a
                    grad[r2, c0] -= a
                    b = (sy * fy[r, c] - cy * (gy[r, c] - my)) / 8.0
                    grad[r2, c0] += b
                    grad[r0, c0] -= b
                    grad[r2, c] += 2.0 * b
                    grad[r0, c] -= 2.0 * b
                    grad[r2, c2] += b
                    grad[r0, c2] -= b

    return kernel
