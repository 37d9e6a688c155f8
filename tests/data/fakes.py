"""Small datasets in the field's format, built with plain torch.save (no project writer)."""

import math
from pathlib import Path

import numpy as np
import torch

from usplat_dr.data.chunks import encode_image


def w2c_rows(c2w: np.ndarray) -> np.ndarray:
    """[V, 12] world-to-camera 3x4 rows, computed with numpy (independent of the loader)."""
    return np.stack([np.linalg.inv(m)[:3].reshape(-1) for m in c2w])


def random_poses(n: int, rng: np.random.Generator) -> np.ndarray:
    """[n, 4, 4] random camera-to-world matrices (proper rotations)."""
    out = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        q, r = np.linalg.qr(rng.normal(size=(3, 3)))
        q *= np.sign(np.diag(r))
        if np.linalg.det(q) < 0:
            q[:, 0] *= -1
        out[i, :3, :3] = q
        out[i, :3, 3] = rng.normal(size=3)
    return out


def fake_scene(key: str, views: int, shape=(360, 640), fmt: str = "jpeg", seed: int = 0,
               fx: float = 0.5) -> dict:
    """A scene dict of the documented structure with random images and poses."""
    rng = np.random.default_rng(seed)
    h, w = shape
    c2w = random_poses(views, rng)
    cams = np.zeros((views, 18), dtype=np.float32)
    cams[:, 0], cams[:, 1] = fx, fx * w / h
    cams[:, 2:4] = 0.5
    cams[:, 6:] = w2c_rows(c2w)
    images = []
    for _ in range(views):
        img = (rng.random((h // 8, w // 8, 3)) * 255).astype(np.uint8).repeat(8, 0).repeat(8, 1)
        images.append(encode_image(img, fmt))
    return {"key": key, "url": f"https://example.com/{key}",
            "timestamps": torch.arange(views, dtype=torch.int64) * 33_366,
            "cameras": torch.from_numpy(cams), "images": images}


def write_plain_dataset(root: Path, stage: str, chunks: list[list[dict]],
                        index: dict | None = None) -> Path:
    """Write chunks with plain torch.save and an index.json, as the field's converters do."""
    import json

    stage_dir = Path(root) / stage
    stage_dir.mkdir(parents=True, exist_ok=True)
    auto = {}
    for i, scenes in enumerate(chunks):
        torch.save(scenes, stage_dir / f"{i:06d}.torch")
        auto.update({s["key"]: f"{i:06d}.torch" for s in scenes
                     if isinstance(s, dict) and isinstance(s.get("key"), str)})
    (stage_dir / "index.json").write_text(json.dumps(auto if index is None else index))
    return stage_dir


def fov_deg(fx: float) -> float:
    return math.degrees(2 * math.atan(0.5 / fx))
