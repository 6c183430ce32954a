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
    FILL_CRACK_PX,
    MIN_SPLAT_WEIGHT,
    NEAR_PLANE,
    OPAQUE_ALPHA,
    SOFT_Z_DISPARITY_PX,
    PointCloud,
)

BATCH_ENTRIES_CPU = 1 << 23
"""Point-frame pairs one launch may hold on torch's CPU device: 7.8 M pairs (three 1920x1080
frames of photo 33) took the process's peak memory from 1.66 to 3.02 GB."""

BATCH_ENTRIES_PER_GIB = 1 << 21
"""Point-frame pairs one launch may hold per GiB of free GPU memory: 512 bytes each, twice
the peak measured on the CPU device (about 175 to 260 bytes per pair)."""

MAX_FRAMES_PER_LAUNCH = 32
"""More frames per launch stop paying once the GPU is busy; this bounds the latency."""


@dataclass(frozen=True)
class _Splats:
    """The bilinear corners of points first..last-1 in a batch of B frames: one entry per
    frame and point (no compaction, which costs more than it saves), per corner the target
    pixel (an index into B x H x W, or the sink just past it where the corner is off the
    frame, the point not visible or the weight negligible) and the weight (0 at the sink)."""

    pixels: list[torch.Tensor]  # 4 x (B * M,) int64
    weights: list[torch.Tensor]  # 4 x (B * M,) float32
    inv_z: torch.Tensor  # (B * M,) float32
    frames: int
    first: int
    last: int

    def values(self, colour: torch.Tensor, weight: torch.Tensor,
               premultiplied: torch.Tensor) -> torch.Tensor:
        """(B * M, 4) rows to accumulate: colour x premultiplied weight, then the weight."""
        rows = torch.empty((self.frames, self.last - self.first, 4), dtype=torch.float32,
                           device=colour.device)
        torch.mul(colour[self.first:self.last][None],
                  premultiplied.view(self.frames, -1, 1), out=rows[..., :3])
        rows[..., 3] = weight.view(self.frames, -1)
        return rows.view(-1, 4)


def _scatter_max(out: torch.Tensor, pixel: torch.Tensor, values: torch.Tensor) -> None:
    out.scatter_reduce_(0, pixel, values, reduce="amax", include_self=True)


class TorchRenderer:
    """One clip's point cloud on a torch device, rendering batches of views of one size.

    disparity_scale has render()'s meaning (tolerances in working disparity pixels)."""

    def __init__(self, cloud: PointCloud, device: torch.device | str,
                 disparity_scale: float) -> None:
        self.device = torch.device(device)

        def upload(array: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(array)).to(self.device, dtype)

        self.xyz = upload(np.stack([cloud.x, cloud.y, cloud.z]), torch.float32)
        self.colour = upload(cloud.colour, torch.float32)
        self.alpha = upload(cloud.alpha, torch.float32) / 255.0
        self.opaque_count = cloud.opaque_count
        self.soft_z = float(np.float32(SOFT_Z_DISPARITY_PX / disparity_scale))
        self.crack_z = float(np.float32(CRACK_DISPARITY_PX / disparity_scale))

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
        _project_chunk and _corner, with the same float32 arithmetic)."""
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
        del depth
        x0 = px.floor()
        y0 = py.floor()
        fx = px - x0
        fy = py - y0
        del px, py
        x0 = x0.to(torch.int32)
        y0 = y0.to(torch.int32)
        size = len(views) * height * width
        base = torch.arange(len(views), device=self.device)[:, None] * (height * width)
        pixels, weights = [], []
        for dy in (0, 1):
            for dx in (0, 1):
                xx = x0 + dx
                yy = y0 + dy
                weight = (fx if dx else 1 - fx) * (fy if dy else 1 - fy)
                keep = (visible & (xx >= 0) & (xx < width) & (yy >= 0) & (yy < height)
                        & (weight > MIN_SPLAT_WEIGHT))
                pixel = torch.where(keep, base + yy.to(torch.int64) * width + xx, size)
                pixels.append(pixel.view(-1))
                weights.append(torch.where(keep, weight, 0.0).view(-1))
        return _Splats(pixels, weights, inv_z.view(-1), len(views), first, last)

    def _splat_opaque(self, views: Sequence[View], height: int, width: int
                      ) -> tuple[torch.Tensor, torch.Tensor]:
        """The opaque points' soft z-buffer, exactly as the sequential kernel decides it.

        In cloud order, a pixel's front is the running maximum M of the inverse depths that
        reached it; a point restarts the pixel when it is nearer than M by more than the
        tolerance, blends in when within it, and is hidden otherwise. So the points kept are
        those from the last restart on that were within the tolerance of M when they came.
        Sorting the splats by pixel, then by point, turns M into a prefix maximum (the pixel
        in the high bits of the key restarts it at every new pixel). Returns each pixel's
        front (inverse depth, 0: none) and its summed colour x weight and weight, each with
        a sink entry at the end."""
        size = len(views) * height * width
        splats = self._project(views, 0, self.opaque_count, height, width)
        points_per_frame = self.opaque_count
        pixel = torch.cat(splats.pixels)
        entry = (pixel < size).nonzero().squeeze(1)
        pixel = pixel[entry]
        weight = torch.cat(splats.weights)[entry]
        all_inv_z = splats.inv_z
        del splats
        frame_point = entry % (len(views) * points_per_frame)
        point = frame_point % points_per_frame
        order = (pixel * points_per_frame + point).argsort()
        pixel, weight, point = pixel[order], weight[order], point[order]
        inv_z = all_inv_z[frame_point[order]]
        del entry, frame_point, order, all_inv_z
        # Running maximum per pixel: the key's high bits are the pixel, its low bits the
        # float's bit pattern (ordered as the value, for positive floats).
        key = (pixel << 32) | inv_z.view(torch.int32).to(torch.int64)
        running = (key.cummax(0).values & 0xFFFFFFFF).to(torch.int32).view(torch.float32)
        first = torch.ones_like(pixel, dtype=torch.bool)
        first[1:] = pixel[1:] != pixel[:-1]
        before = torch.zeros_like(inv_z)
        before[1:] = running[:-1]
        before = torch.where(first, 0.0, before)  # the front when the point arrived
        del key, running
        restart = first | (before < inv_z - self.soft_z)
        index = torch.arange(pixel.shape[0], device=self.device)
        latest = torch.where(restart, index, -1).cummax(0).values
        last_restart = torch.full((size + 1,), -1, dtype=torch.int64, device=self.device)
        last_restart.scatter_reduce_(0, pixel, latest, reduce="amax", include_self=True)
        kept = (index >= last_restart[pixel]) & (before <= inv_z + self.soft_z)
        del restart, latest, last_restart, index, before, first
        weight = torch.where(kept, weight, 0.0)
        front = torch.zeros(size + 1, dtype=torch.float32, device=self.device)
        _scatter_max(front, pixel, inv_z)
        rows = torch.empty((pixel.shape[0], 4), dtype=torch.float32, device=self.device)
        torch.mul(self.colour[point], weight[:, None], out=rows[:, :3])
        rows[:, 3] = weight
        cell = torch.zeros((size + 1, 4), dtype=torch.float32, device=self.device)
        return front, cell.index_add_(0, pixel, rows)

    def _render(self, views: Sequence[View], height: int, width: int) -> torch.Tensor:
        size = len(views) * height * width

        def zeros(*shape: int) -> torch.Tensor:  # per pixel, plus the sink
            return torch.zeros((size + 1, *shape), dtype=torch.float32, device=self.device)

        soft_z = self.soft_z
        front_opaque, cell_opaque = self._splat_opaque(views, height, width)

        # Soft points: either a new front clearly before the opaque one (which then is the
        # surface behind), or blended into it; farther ones z-buffered into the surface behind.
        soft = self._project(views, self.opaque_count, len(self), height, width)
        alpha = self.alpha[self.opaque_count:][None].expand(len(views), -1).reshape(-1)
        front_soft = zeros()
        for pixel in soft.pixels:
            _scatter_max(front_soft, pixel, soft.inv_z)
        soft_front = front_soft > front_opaque + soft_z
        lowest = torch.where(soft_front, front_soft, front_opaque) - soft_z
        cell_soft, clear, blended_front, back_soft = zeros(4), zeros(), zeros(), zeros()
        for pixel, weight in zip(soft.pixels, soft.weights, strict=True):
            in_front = soft.inv_z >= lowest[pixel]
            w = torch.where(in_front, weight, 0.0)
            wa = w * alpha
            cell_soft.index_add_(0, pixel, soft.values(self.colour, w, wa))
            clear.index_add_(0, pixel, w - wa)
            _scatter_max(blended_front, pixel, torch.where(in_front, soft.inv_z, 0.0))
            behind = ~in_front & (weight * alpha > MIN_SPLAT_WEIGHT)
            _scatter_max(back_soft, pixel, torch.where(behind, soft.inv_z, 0.0))
        back = torch.maximum(torch.where(soft_front, front_opaque, 0.0), back_soft)
        back_cell = zeros(4)
        for pixel, weight in zip(soft.pixels, soft.weights, strict=True):
            behind = ((soft.inv_z < lowest[pixel]) & (weight * alpha > MIN_SPLAT_WEIGHT)
                      & (soft.inv_z >= back[pixel] - soft_z))
            wa = torch.where(behind, weight * alpha, 0.0)
            back_cell.index_add_(0, pixel, soft.values(self.colour, wa, wa))
        del soft, alpha
        opaque_behind = soft_front & (front_opaque > 0) & (front_opaque >= back - soft_z)
        back_cell += torch.where(opaque_behind[:, None], cell_opaque, 0.0)
        cell = torch.where(soft_front[:, None], cell_soft, cell_opaque + cell_soft)[:size]
        on_opaque = (front_opaque > 0)[:size]
        front = torch.where(soft_front, front_soft, torch.maximum(front_opaque, blended_front))
        del cell_opaque, cell_soft, front_opaque, front_soft, blended_front, lowest
        front, clear, back, back_cell = front[:size], clear[:size], back[:size], back_cell[:size]
        soft_pixel = clear > 0
        back = torch.where(soft_pixel, back, 0.0)

        total = cell[:, 3]
        # Crack filter on the solid surfaces: a mostly see-through fringe shows what is behind.
        see_through = soft_pixel & (total - clear < 0.5 * total)
        solid = torch.where(see_through, back, front).view(len(views), height, width)
        cracked = _cracks(solid, self.crack_z).view(-1) & ~soft_pixel
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
        # A soft edge over nothing is filled as a hole, from the surfaces behind the soft
        # pixels around it, and composited over that fill (one blended into an opaque
        # surface at its depth keeps its own colour).
        over_nothing = (soft_pixel & (back <= 0) & ~on_opaque & (front > 0)
                        & (front_alpha < OPAQUE_ALPHA))
        front = torch.where(over_nothing, 0.0, front)
        shape = (len(views), height, width)
        image = _fill_from_background(image.view(*shape, 3), front.view(shape))
        if not bool(over_nothing.any()):
            return image
        behind_soft = soft_pixel & (back > 0)
        behind = torch.where(behind_soft[:, None],
                             back_cell[:, :3] / back_cell[:, 3:].clamp(min=MIN_SPLAT_WEIGHT ** 2),
                             image.view(-1, 3).float())
        solid = torch.where(behind_soft, back, front)
        behind = _fill_from_background(behind.view(*shape, 3), front.view(shape),
                                       solid.view(shape)).view(-1, 3)
        premultiplied = cell[:, :3] / total.clamp(min=MIN_SPLAT_WEIGHT)[:, None]
        veil = premultiplied + (1 - front_alpha)[:, None] * behind
        veil = (veil + 0.5).floor().clamp(0, 255).to(torch.uint8)
        return torch.where(over_nothing[:, None], veil, image.view(-1, 3)).view(*shape, 3)


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


def _fill_from_background(image: torch.Tensor, front: torch.Tensor,
                          solid: torch.Tensor | None = None) -> torch.Tensor:
    """Every empty pixel (front 0) takes the colour of the farthest covered pixel among the
    nearest ones to its left, right, above and below (render's finishing fill); farthest by
    solid, the depth of what lies behind a soft pixel, where given."""
    empty = front <= 0
    holes = empty.view(-1).nonzero().squeeze(1)
    if holes.numel() == 0:
        return image
    frames, height, width = front.shape
    device = front.device
    hole_x = holes % width
    hole_y = holes // width % height
    flat_front = (front if solid is None else solid).reshape(-1)
    candidates_front, candidates_index, candidates_near = [], [], []
    for dim, reverse in ((2, False), (2, True), (1, False), (1, True)):
        length = front.shape[dim]
        shape = [1, 1, 1]
        shape[dim] = length
        positions = torch.arange(length, device=device, dtype=torch.int32).view(shape)
        if reverse:  # nearest after: the nearest before, counted from the other end
            positions = length - 1 - positions
        marked = torch.where(empty, -1, positions)
        if reverse:
            found = marked.flip(dim).cummax(dim).values.flip(dim)
        else:
            found = marked.cummax(dim).values
        step = found.view(-1)[holes].to(torch.int64)
        valid = step >= 0
        at = length - 1 - step if reverse else step  # the covered pixel's column or row
        index = (holes + (at - hole_x) if dim == 2 else holes + (at - hole_y) * width)
        index = torch.where(valid, index, 0)
        candidates_front.append(torch.where(valid, flat_front[index], float("inf")))
        candidates_index.append(torch.where(valid, index, -1))
        here = hole_x if dim == 2 else hole_y
        candidates_near.append(valid & ((at - here).abs() <= FILL_CRACK_PX))
    # A crack (covered on both sides of a row or a column, close by) is closed from those two
    # sides, as render's finishing fill does.
    crack_h = candidates_near[0] & candidates_near[1]
    crack_v = candidates_near[2] & candidates_near[3]
    crack = crack_h | crack_v
    for k, in_pair in enumerate((crack_h, crack_h, crack_v, crack_v)):
        candidates_front[k] = torch.where(crack & ~in_pair, float("inf"), candidates_front[k])
    choice = torch.stack(candidates_front).argmin(dim=0, keepdim=True)  # ties: the first
    source = torch.stack(candidates_index).gather(0, choice)[0]
    flat = image.view(-1, 3).clone()
    flat[holes] = torch.where((source >= 0)[:, None], flat[source.clamp(min=0)], 0)
    return flat.view(image.shape)


def render_batches(cloud: PointCloud, views: Sequence[View], disparity_scale: float,
                   device: str, output_size: tuple[int, int] | None = None
                   ) -> Iterator[np.ndarray]:
    """Finished frames of a clip in launches of several: (B, H, W, 3) uint8 arrays in the
    order of views. The cloud goes to the device once, before the first launch. With
    output_size (width, height), frames rendered smaller (pipeline.render_view) are enlarged
    to it with linear interpolation, as cv2.resize does; a launch holds views of one size."""
    renderer = TorchRenderer(cloud, device, disparity_scale)
    step = renderer.frames_per_launch()
    start = 0
    while start < len(views):
        size = (views[start].width_px, views[start].height_px)
        stop = start + 1
        while (stop < len(views) and stop - start < step
               and (views[stop].width_px, views[stop].height_px) == size):
            stop += 1
        frames = renderer.render_frames(views[start:stop])
        if output_size is not None and size != output_size:
            frames = _enlarged(frames, output_size)
        yield frames.cpu().numpy()
        start = stop


def _enlarged(frames: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """(B, h, w, 3) uint8 frames enlarged to size (width, height), linearly."""
    planar = frames.permute(0, 3, 1, 2).float()
    planar = torch.nn.functional.interpolate(planar, size=(size[1], size[0]), mode="bilinear",
                                             align_corners=False)
    return (planar + 0.5).floor().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1)
