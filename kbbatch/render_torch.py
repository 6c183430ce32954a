"""The frame renderer of kbbatch.render as torch tensor operations: its GPU backend.

The same design in a second backend: project the cloud, soft-z splat the opaque points
bilinearly, then the soft points of the layers' edges, each keeping the surface behind it;
crack filter; composite with premultiplied alpha; fill the few empty pixels from the
background side. The numba kernels splat point after point; here every step is a scatter over
all points of several frames at once (one launch renders a batch of frames), so the soft
z-buffer is decided per pixel from the nearest surface found by a max-scatter first: a point
blends in when it lies within SOFT_Z_DISPARITY_PX of the pixel's final front, where the
sequential kernel compares with the front as it stood when the point arrived. The two differ
only where a chain of points each within the tolerance of the last spans more than it; the
frames agree to well above 50 dB PSNR (tests/test_render_torch.py).

The cloud is uploaded once per clip (TorchRenderer); frames come back as uint8.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from kbbatch.camera import View
from kbbatch.render import (
    CRACK_DISPARITY_PX,
    MIN_SPLAT_WEIGHT,
    NEAR_PLANE,
    OPAQUE_ALPHA,
    SOFT_Z_DISPARITY_PX,
    PointCloud,
)

BATCH_ENTRIES_CPU = 1 << 25
"""Point-frame pairs one launch may hold on torch's CPU device (each costs about 60 bytes in
the intermediate tensors: 32 M pairs are about 2 GB)."""

BATCH_ENTRIES_PER_GIB = 1 << 23
"""Point-frame pairs one launch may hold per GiB of free GPU memory (with the same margin)."""

MAX_FRAMES_PER_LAUNCH = 32
"""More frames per launch stop paying once the GPU is busy; this bounds the latency."""


@dataclass(frozen=True)
class _Splats:
    """Bilinear corners of visible points in a batch of frames, flattened: target pixel (index
    into B x H x W), bilinear weight, the point's inverse depth and its index in the cloud."""

    pixel: torch.Tensor  # int64
    weight: torch.Tensor  # float32
    inv_z: torch.Tensor  # float32
    point: torch.Tensor  # int64


def _scatter_max(size: int, index: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    out = torch.zeros(size, dtype=torch.float32, device=values.device)
    return out.scatter_reduce_(0, index, values, reduce="amax", include_self=True)


def _scatter_sum(size: int, index: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    shape = (size, *values.shape[1:])
    return torch.zeros(shape, dtype=torch.float32, device=values.device).index_add_(0, index,
                                                                                  values)


class TorchRenderer:
    """One clip's point cloud on a torch device, rendering batches of views of one size.

    disparity_scale has render()'s meaning (tolerances in working disparity pixels)."""

    def __init__(self, cloud: PointCloud, device: torch.device | str,
                 disparity_scale: float) -> None:
        self.device = torch.device(device)
        opaque = cloud.opaque_count

        def upload(array: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(array)).to(self.device, dtype)

        self.xyz = upload(np.stack([cloud.x, cloud.y, cloud.z]), torch.float32)
        self.colour = upload(cloud.colour, torch.float32)
        self.alpha = upload(cloud.alpha, torch.float32) / 255.0
        self.opaque_count = opaque
        self.soft_z = np.float32(SOFT_Z_DISPARITY_PX / disparity_scale)
        self.crack_z = np.float32(CRACK_DISPARITY_PX / disparity_scale)

    def __len__(self) -> int:
        return int(self.xyz.shape[1])

    def frames_per_launch(self) -> int:
        """Frames that one launch can render within the memory budget."""
        if self.device.type == "cuda":
            free_bytes, _ = torch.cuda.mem_get_info(self.device)
            budget = int(free_bytes / 2**30 * BATCH_ENTRIES_PER_GIB)
        else:
            budget = BATCH_ENTRIES_CPU
        return int(max(1, min(MAX_FRAMES_PER_LAUNCH, budget // max(1, len(self)))))

    def render_frames(self, views: Sequence[View]) -> torch.Tensor:
        """Finished frames (B, H, W, 3) uint8 on the device, as render_frame() makes them."""
        height, width = views[0].height_px, views[0].width_px
        if any((v.height_px, v.width_px) != (height, width) for v in views):
            raise ValueError("all views of a launch must have the same size")
        with torch.inference_mode():
            return self._render(views, height, width)

    def _project(self, views: Sequence[View], first: int, last: int, height: int,
                 width: int) -> _Splats:
        """Bilinear corners of points first..last-1 in every view (kbbatch.render's
        _project_chunk and _corner): visible points, corners inside and weighted enough."""
        def column(values: list[float]) -> torch.Tensor:
            return torch.tensor(values, dtype=torch.float32, device=self.device)[:, None]

        cam_x = column([v.position[0] for v in views])
        cam_y = column([v.position[1] for v in views])
        cam_z = column([v.position[2] for v in views])
        focal = column([v.focal_px for v in views])
        ppx = column([v.principal_x_px - 0.5 for v in views])
        ppy = column([v.principal_y_px - 0.5 for v in views])
        x, y, z = self.xyz[:, first:last]
        depth = z[None] - cam_z
        inv_z = 1.0 / depth.clamp(min=NEAR_PLANE)
        px = focal * (x[None] - cam_x) * inv_z + ppx
        py = focal * (y[None] - cam_y) * inv_z + ppy
        visible = (depth > NEAR_PLANE) & (px > -1) & (py > -1) & (px < width) & (py < height)
        frame, point = visible.nonzero(as_tuple=True)
        px, py, inv_z = px[frame, point], py[frame, point], inv_z[frame, point]
        del visible, depth
        x0 = px.floor()
        y0 = py.floor()
        fx = px - x0
        fy = py - y0
        x0 = x0.to(torch.int64)
        y0 = y0.to(torch.int64)
        base = frame * (height * width)
        pixels, weights, inv_zs, points = [], [], [], []
        for dy in (0, 1):
            for dx in (0, 1):
                xx = x0 + dx
                yy = y0 + dy
                weight = (fx if dx else 1 - fx) * (fy if dy else 1 - fy)
                keep = ((xx >= 0) & (xx < width) & (yy >= 0) & (yy < height)
                        & (weight > MIN_SPLAT_WEIGHT))
                pixels.append((base + yy * width + xx)[keep])
                weights.append(weight[keep])
                inv_zs.append(inv_z[keep])
                points.append((point + first)[keep])
        return _Splats(torch.cat(pixels), torch.cat(weights), torch.cat(inv_zs),
                       torch.cat(points))

    def _render(self, views: Sequence[View], height: int, width: int) -> torch.Tensor:
        size = len(views) * height * width
        soft_z = float(self.soft_z)
        # Opaque points: a soft z-buffer, the front being the nearest surface of the pixel.
        opaque = self._project(views, 0, self.opaque_count, height, width)
        front_opaque = _scatter_max(size, opaque.pixel, opaque.inv_z)
        blends = opaque.inv_z >= front_opaque[opaque.pixel] - soft_z
        weight = opaque.weight[blends]
        cell_opaque = _scatter_sum(size, opaque.pixel[blends], torch.cat(
            [self.colour[opaque.point[blends]] * weight[:, None], weight[:, None]], dim=1))
        del opaque, blends, weight

        # Soft points: either a new front clearly before the opaque one (which then is the
        # surface behind), or blended into it; farther ones z-buffered into the surface behind.
        soft = self._project(views, self.opaque_count, len(self), height, width)
        front_soft = _scatter_max(size, soft.pixel, soft.inv_z)
        soft_front = front_soft > front_opaque + soft_z
        lowest = torch.where(soft_front, front_soft, front_opaque) - soft_z
        alpha = self.alpha[soft.point]
        colour = self.colour[soft.point]
        in_front = soft.inv_z >= lowest[soft.pixel]
        w = soft.weight[in_front]
        wa = w * alpha[in_front]
        pixel = soft.pixel[in_front]
        cell_soft = _scatter_sum(size, pixel, torch.cat([colour[in_front] * wa[:, None],
                                                         w[:, None]], dim=1))
        clear = _scatter_sum(size, pixel, w - wa)
        blended_front = _scatter_max(size, pixel, soft.inv_z[in_front])
        behind = ~in_front & (soft.weight * alpha > MIN_SPLAT_WEIGHT)
        back_soft = _scatter_max(size, soft.pixel[behind], soft.inv_z[behind])
        back = torch.maximum(torch.where(soft_front, front_opaque, 0.0), back_soft)
        behind &= soft.inv_z >= back[soft.pixel] - soft_z
        wa = soft.weight[behind] * alpha[behind]
        back_cell = _scatter_sum(size, soft.pixel[behind],
                                 torch.cat([colour[behind] * wa[:, None], wa[:, None]], dim=1))
        del soft, alpha, colour, in_front, behind, w, wa, pixel
        opaque_behind = soft_front & (front_opaque > 0) & (front_opaque >= back - soft_z)
        back_cell += torch.where(opaque_behind[:, None], cell_opaque, 0.0)
        cell = torch.where(soft_front[:, None], cell_soft, cell_opaque + cell_soft)
        front = torch.where(soft_front, front_soft, torch.maximum(front_opaque, blended_front))
        del cell_opaque, cell_soft, front_opaque, front_soft, blended_front, lowest
        soft_pixel = clear > 0
        back = torch.where(soft_pixel, back, 0.0)

        total = cell[:, 3]
        # Crack filter on the solid surfaces: a mostly see-through fringe shows what is behind.
        see_through = soft_pixel & (total - clear < 0.5 * total)
        solid = torch.where(see_through, back, front).view(len(views), height, width)
        cracked = _cracks(solid, float(self.crack_z)).view(-1) & ~soft_pixel
        front = torch.where(cracked, 0.0, front)

        # Composite: premultiplied front over the back where the front is a soft edge.
        alpha_sum = (total - clear).clamp(min=0.0)
        front_alpha = alpha_sum / total.clamp(min=MIN_SPLAT_WEIGHT)
        over_back = soft_pixel & (back > 0) & (front_alpha < OPAQUE_ALPHA)
        opaque_colour = cell[:, :3] / total.clamp(min=MIN_SPLAT_WEIGHT)[:, None]
        back_scale = (1 - front_alpha) / back_cell[:, 3].clamp(min=MIN_SPLAT_WEIGHT ** 2)
        composite = opaque_colour + back_cell[:, :3] * back_scale[:, None]
        own = cell[:, :3] / alpha_sum.clamp(min=MIN_SPLAT_WEIGHT ** 2)[:, None]
        colour = torch.where(over_back[:, None], composite,
                             torch.where(soft_pixel[:, None], own, opaque_colour))
        image = (colour + 0.5).floor().clamp(0, 255).to(torch.uint8)
        image = image.view(len(views), height, width, 3)
        return _fill_from_background(image, front.view(len(views), height, width))


def _cracks(solid: torch.Tensor, crack_z: float) -> torch.Tensor:
    """Pixels (not on the frame's border) whose two opposite neighbours, in any of four
    directions, are nearer by crack_z: background seen through a crack (render's filter)."""
    centre = solid[:, 1:-1, 1:-1] + crack_z
    found = torch.zeros_like(solid, dtype=torch.bool)
    inner = found[:, 1:-1, 1:-1]
    height, width = solid.shape[1:]
    for (ay, ax), (by, bx) in (((1, 0), (1, 2)), ((0, 1), (2, 1)), ((0, 0), (2, 2)),
                               ((0, 2), (2, 0))):
        first = solid[:, ay:ay + height - 2, ax:ax + width - 2]
        second = solid[:, by:by + height - 2, bx:bx + width - 2]
        inner |= (first > centre) & (second > centre)
    return found


def _fill_from_background(image: torch.Tensor, front: torch.Tensor) -> torch.Tensor:
    """Every empty pixel (front 0) takes the colour of the farthest covered pixel among the
    nearest ones to its left, right, above and below (render's finishing fill)."""
    empty = front <= 0
    if not bool(empty.any()):
        return image
    frames, height, width = front.shape
    columns = torch.arange(width, device=front.device).expand(frames, height, width)
    rows = torch.arange(height, device=front.device)[:, None].expand(frames, height, width)
    inf = torch.tensor(float("inf"), device=front.device)

    def nearest(positions: torch.Tensor, dim: int, flip: bool) -> torch.Tensor:
        """Position of the nearest covered pixel before each pixel along dim (-1: none)."""
        marked = torch.where(empty, -1, positions)
        if flip:
            size = positions.shape[dim]
            marked = torch.where(empty, -1, size - 1 - positions).flip(dim)
            found = marked.cummax(dim).values.flip(dim)
            return torch.where(found >= 0, size - 1 - found, -1)
        return marked.cummax(dim).values

    candidates_front = []
    candidates_index = []
    flat_base = torch.arange(frames, device=front.device)[:, None, None] * (height * width)
    for positions, dim, flip in ((columns, 2, False), (columns, 2, True), (rows, 1, False),
                                 (rows, 1, True)):
        found = nearest(positions, dim, flip)
        valid = found >= 0
        safe = found.clamp(min=0)
        index = flat_base + (safe if dim == 1 else rows) * width + (columns if dim == 1 else safe)
        value = torch.where(valid, front.reshape(-1)[index], inf)
        candidates_front.append(value)
        candidates_index.append(torch.where(valid, index, -1))
    values = torch.stack(candidates_front)
    choice = values.argmin(dim=0, keepdim=True)  # ties: the first (left, right, up, down)
    source = torch.stack(candidates_index).gather(0, choice)[0]
    flat = image.reshape(-1, 3)
    fill = torch.where((source >= 0)[..., None], flat[source.clamp(min=0)],
                       torch.zeros((), dtype=image.dtype, device=image.device))
    return torch.where(empty[..., None], fill, image)


def render_batches(cloud: PointCloud, views: Sequence[View], disparity_scale: float,
                   device: str) -> Iterator[np.ndarray]:
    """Finished frames of a clip in launches of several: (B, H, W, 3) uint8 arrays in the
    order of views. The cloud goes to the device once, before the first launch."""
    renderer = TorchRenderer(cloud, device, disparity_scale)
    step = renderer.frames_per_launch()
    for start in range(0, len(views), step):
        yield renderer.render_frames(views[start:start + step]).cpu().numpy()
