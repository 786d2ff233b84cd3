"""The maze teacher's LSTM input projection, computed exactly from the few cells its grid changes per step.

The teacher's LSTM input at step t is x_t = [f(I_t), e_t]: f(I) = ReLU(conv(I / scale)) flattened as
(channel, y, x), C channels at P output positions, the conv features of the grid image I_t; e_t the small
dense rest (time embedding, noise). Its projection splits as W_ih x_t = W f(I_t) + V e_t. A teacher step
changes at most one cell of the image (a wall, the goal, or a wall cleared under the agent, which the
image does not show), and the conv output at a position depends only on the k x k cells of its window,
so with the changes Δ_s = f(I_s) - f(I_{s-1}) (I_{-1} a reference image: the batch's first image, the
empty grid every teacher episode starts from):

    W f(I_t) = W f(I_ref) + sum_{s <= t} W Δ_s,

each Δ_s nonzero only at the positions whose window holds a cell that differs between I_s and I_{s-1}
(found by comparing the images, whatever changed them). The sum is exact for any images; it is cheap when
few windows change. Forward: for each output position p, one product of the changes there [E_p, C] with
that position's weights [C, 4H] (the reference's features at p, shared by the whole batch, as one more
row), the products added into their steps, and a cumulative sum over time. For the paper's teacher
(C = 128, P = 169) one changed cell touches 9 of 169 positions.

Backward, with g_t the gradient of W_ih x_t and R_s = sum_{t >= s} g_t (a reverse cumulative sum):

    dL/dW = (sum_t g_t) f(I_ref)^T + sum_s R_s Δ_s^T    (Δ_s's nonzero columns only)
    dL/df(I_ref) = W^T sum_t g_t,    dL/dΔ_s = W^T R_s   (at Δ_s's nonzero entries)
    dL/dV = sum_t g_t e_t^T,         dL/de_t = V^T g_t.

dL/dΔ flows on through the ReLU and the conv at those positions only (autograd, from the patches under
the changed windows). Acting keeps W f(I) per env copy from step to step and adds the changed windows'
share (`RunningConvGates`).

Rows are time-major: a training batch is [T * N], row t * N + n is step t of env copy n.
"""

from __future__ import annotations

import torch
from torch import nn

# Above this share of changed (step, position) windows the sparse path stops paying (its per-window
# buffers outgrow the dense path's); callers then project densely.
MAX_CHANGED_FRACTION = 1 / 8


def conv_features(conv: nn.Conv2d, images: torch.Tensor, scale: float) -> torch.Tensor:
    """The dense features f(I) = ReLU(conv(I / scale)) flattened as (channel, y, x), of images
    [B, H, W, channels]: [B, C * P]."""
    return torch.relu(conv(images.permute(0, 3, 1, 2).to(conv.weight.dtype) / scale)).flatten(1)


def changed_windows(images: torch.Tensor, previous: torch.Tensor, kernel: int) -> torch.Tensor:
    """Which conv windows ([B, H - k + 1, W - k + 1] bool) hold a cell that differs between `images`
    and `previous` ([B, H, W, channels] each): the output positions whose features may differ."""
    changed_cells = (images != previous).any(-1).unsqueeze(1).float()
    return nn.functional.max_pool2d(changed_cells, kernel, stride=1).squeeze(1) > 0


def features_at(conv: nn.Conv2d, images: torch.Tensor, rows: torch.Tensor, ys: torch.Tensor, xs: torch.Tensor, scale: float) -> torch.Tensor:
    """f(I) at output position (ys[e], xs[e]) of image rows[e] of `images` [B, H, W, channels], for
    every e: the conv's patch product there, ReLU'd: [E, C] (with gradient to the conv)."""
    _, height, width, channels = images.shape
    kernel = conv.kernel_size[0]
    channel, ky, kx = torch.meshgrid(*(torch.arange(n, device=images.device) for n in (channels, kernel, kernel)), indexing="ij")
    offsets = ((ky * width + kx) * channels + channel).reshape(-1)  # in the order of conv.weight [C, channels, ky, kx]
    corners = ((rows * height + ys) * width + xs) * channels
    patches = images.reshape(-1)[corners.unsqueeze(1) + offsets].to(conv.weight.dtype) / scale
    return torch.relu(torch.addmm(conv.bias, patches, conv.weight.reshape(len(conv.weight), -1).t()))


def cumulative_sum_(steps: torch.Tensor, reverse: bool = False) -> torch.Tensor:
    """In place, over the first dimension (time): x_t <- sum_{s <= t} x_s, or with `reverse` sum_{s >= t}.
    A loop of adds: torch.cumsum along a leading dimension is many times slower on CPU."""
    order = range(len(steps) - 2, -1, -1) if reverse else range(1, len(steps))
    for t in order:
        steps[t] += steps[t + 1 if reverse else t - 1]
    return steps


def position_groups(positions: torch.Tensor, num_positions: int) -> list[tuple[int, int, int]]:
    """(position, start, end) for every position with entries: where its entries lie once sorted by position."""
    counts = torch.bincount(positions, minlength=num_positions).tolist()
    groups, start = [], 0
    for position, count in enumerate(counts):
        if count:
            groups.append((position, start, start + count))
            start += count
    return groups


def position_products(values: torch.Tensor, groups: list, weights: torch.Tensor, transpose: bool = False) -> torch.Tensor:
    """Each entry's values times its position's weights: values [E, C] @ weights[:, p] [C, 4H] -> [E, 4H],
    or with `transpose` values [E, 4H] @ weights[:, p]^T -> [E, C]; one matmul per position."""
    out = values.new_empty(len(values), weights.shape[0] if transpose else weights.shape[2])
    for position, start, end in groups:
        block = weights[:, position]
        torch.mm(values[start:end], block.t() if transpose else block, out=out[start:end])
    return out


class SparseInputProjection(torch.autograd.Function):
    """W_ih x_t (without bias) for every row of a time-major batch [T * N], from the reference's
    features f(I_ref) [C * P], the changes Δ at their (row, position) entries [E, C] and the dense
    inputs e_t [T * N, D]; W_ih is [4H, C * P + D]. The equations are the module's.

    The reference joins the changes as one more entry per position, in a virtual row T * N after the
    batch that every step adds (its gradient: sum_t g_t). So each position's weights [C, 4H] are read
    once per product, for its changes and its share of W f(I_ref) together, and the (sum_t g_t) f(I_ref)^T
    term of dL/dW comes out of the same products."""

    @staticmethod
    def forward(ctx, weight_ih, start_features, deltas, dense_inputs, rows, positions, num_copies):
        four_h, conv_size = weight_ih.shape[0], start_features.numel()
        channels, num_rows = deltas.shape[1], len(dense_inputs)
        num_positions = conv_size // channels
        # The entries with the reference's, sorted by position (stable: the reference's last in each).
        all_positions = torch.cat([positions, torch.arange(num_positions, device=positions.device)])
        order = torch.sort(all_positions, stable=True).indices
        values = torch.cat([deltas, start_features.view(channels, num_positions).t()]).index_select(0, order)
        all_rows = torch.cat([rows, rows.new_full((num_positions,), num_rows)]).index_select(0, order)
        groups = position_groups(all_positions, num_positions)
        # W_ih^T [F, 4H]: its conv rows [C, P, 4H] give each position's weights as a [C, 4H] matrix. A view
        # if W_ih is stored transposed (the maze teacher's is), else a copy.
        weight_t = weight_ih.t().contiguous()
        conv_weight_t = weight_t[:conv_size].view(channels, num_positions, four_h)
        per_row = weight_ih.new_zeros(num_rows + 1, four_h).index_add_(0, all_rows, position_products(values, groups, conv_weight_t))
        projected = cumulative_sum_(per_row[:num_rows].view(-1, num_copies, four_h)).view(num_rows, four_h)
        projected.add_(per_row[num_rows]).addmm_(dense_inputs, weight_t[conv_size:])
        ctx.save_for_backward(weight_t, values, dense_inputs, all_rows, order)
        ctx.groups, ctx.num_copies, ctx.num_changes = groups, num_copies, len(deltas)
        return projected

    @staticmethod
    def backward(ctx, grad):
        weight_t, values, dense_inputs, all_rows, order = ctx.saved_tensors
        channels, num_positions, four_h = values.shape[1], len(values) - ctx.num_changes, weight_t.shape[1]
        conv_size = channels * num_positions
        conv_weight_t = weight_t[:conv_size].view(channels, num_positions, four_h)
        grad = grad.contiguous()
        remaining = cumulative_sum_(grad.view(-1, ctx.num_copies, four_h).clone(), reverse=True).view(-1, four_h)  # R_s
        total = remaining[: ctx.num_copies].sum(0, keepdim=True)  # sum_t g_t, over all copies: the reference's row
        at_entries = torch.cat([remaining, total]).index_select(0, all_rows)
        grad_weight = grad_start = grad_deltas = grad_dense = None
        if ctx.needs_input_grad[1] or ctx.needs_input_grad[2]:
            grad_values = torch.empty_like(values).index_copy_(0, order, position_products(at_entries, ctx.groups, conv_weight_t, transpose=True))
            grad_deltas = grad_values[: ctx.num_changes]
            grad_start = grad_values[ctx.num_changes :].t().reshape(conv_size)
        if ctx.needs_input_grad[3]:
            grad_dense = grad @ weight_t[conv_size:].t()
        if ctx.needs_input_grad[0]:
            grad_weight_t = torch.empty_like(weight_t)  # dL/dW^T, transposed once at the end
            conv_grad_t = grad_weight_t[:conv_size].view_as(conv_weight_t)
            for position, start, end in ctx.groups:
                torch.mm(values[start:end].t(), at_entries[start:end], out=conv_grad_t[:, position])
            torch.mm(dense_inputs.t(), grad, out=grad_weight_t[conv_size:])
            grad_weight = grad_weight_t.t()  # in W_ih's layout if it is stored transposed; autograd copies it otherwise
        return grad_weight, grad_start, grad_deltas, grad_dense, None, None, None


def sparse_gate_inputs(conv: nn.Conv2d, scale: float, reference: torch.Tensor, images: torch.Tensor, dense_inputs: torch.Tensor,
                       weight_ih: torch.Tensor, bias: torch.Tensor, num_copies: int,
                       max_changed_fraction: float = MAX_CHANGED_FRACTION) -> torch.Tensor | None:
    """The LSTM's gate inputs W_ih x_t + bias [T * N, 4H] of a time-major batch of grid images
    [T * N, H, W, channels] and dense inputs [T * N, D], with I_{-1} = `reference` [H, W, channels];
    None if more than `max_changed_fraction` of the windows change (the dense projection is cheaper)."""
    previous = torch.cat([reference.expand(num_copies, *reference.shape), images[:-num_copies]])
    windows = changed_windows(images, previous, conv.kernel_size[0])
    _, out_height, out_width = windows.shape
    if windows.sum() > max_changed_fraction * windows.numel():
        return None
    entry_rows, ys, xs = windows.nonzero(as_tuple=True)
    deltas = features_at(conv, images, entry_rows, ys, xs, scale) - features_at(conv, previous, entry_rows, ys, xs, scale)
    start_features = conv_features(conv, reference.unsqueeze(0), scale)[0]
    return SparseInputProjection.apply(weight_ih, start_features, deltas, dense_inputs, entry_rows, ys * out_width + xs, num_copies) + bias


class RunningConvGates:
    """Acting (no gradient): W f(I) [N, 4H] of each env copy's current image, carried from step to step.

    Each call compares the new images with the copy's previous ones and adds W Δ of the changed windows
    only. A copy whose image differs from the reference in no more cells than from its previous image
    (a teacher episode's first step) restarts from W f(I_ref), so rounding does not build up over
    episodes; if too many windows change (images from elsewhere), all copies restart from the dense
    product W f(I). A new batch size starts from the reference, and so does the call after `start_over`.
    Built with the weights it was derived from (the acting weights), so it never outlives them:
    `conv_weight_t` is W^T's conv rows as [C, P, 4H], `start_gates` W f(I_ref) [4H]."""

    def __init__(self, conv: nn.Conv2d, scale: float, reference: torch.Tensor, conv_weight_t: torch.Tensor, start_gates: torch.Tensor):
        self.conv, self.scale, self.reference = conv, scale, reference
        self.conv_weight_t, self.start_gates = conv_weight_t, start_gates
        self.start_over()

    def start_over(self) -> None:
        self.images, self.gates = None, None

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        """W f(I) [N, 4H] of images [N, H, W, channels] (a new tensor)."""
        n = len(images)
        if self.images is None or len(self.images) != n:
            self.images = self.reference.expand(n, *self.reference.shape)
            self.gates = self.start_gates.expand(n, -1)
        from_reference = (images != self.reference).any(-1).sum((1, 2))
        from_previous = (images != self.images).any(-1).sum((1, 2))
        rebase = from_reference <= from_previous
        base_images = torch.where(rebase.view(n, 1, 1, 1), self.reference, self.images)
        base_gates = torch.where(rebase.view(n, 1), self.start_gates, self.gates)
        windows = changed_windows(images, base_images, self.conv.kernel_size[0])
        _, out_height, out_width = windows.shape
        if windows.sum() > MAX_CHANGED_FRACTION * windows.numel():
            gates = conv_features(self.conv, images, self.scale) @ self.conv_weight_t.reshape(-1, self.conv_weight_t.shape[2])
        else:
            # Entries position-major, as position_products takes them.
            positions, copies = windows.permute(1, 2, 0).reshape(out_height * out_width, n).nonzero(as_tuple=True)
            ys, xs = positions // out_width, positions % out_width
            deltas = features_at(self.conv, images, copies, ys, xs, self.scale) - features_at(self.conv, base_images, copies, ys, xs, self.scale)
            groups = position_groups(positions, out_height * out_width)
            gates = base_gates.index_add(0, copies, position_products(deltas, groups, self.conv_weight_t))
        self.images, self.gates = images.clone(), gates
        return gates.clone()
