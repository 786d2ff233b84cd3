"""The PPO parts that CarRacing and the walker added to every script, on small worked examples: return
normalization, minibatches of single steps versus whole rollouts, and the value-loss choices."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import paired
import plr


def test_return_normalizer_divides_by_the_running_std_of_the_discounted_return():
    """gamma 0.5, one copy, rewards 1, 1 (ended), 2. Discounted returns seen: 1, 1.5, 2 (reset after the
    end). The running moments, here at mean 0, var 4, count 100, absorb each value in turn (Chan et
    al.'s parallel update with a batch of one: its own variance is 0)."""
    normalizer = plr.ReturnNormalizer(num_envs=1, gamma=0.5)
    normalizer.mean, normalizer.var, normalizer.count = 0.0, 4.0, 100.0
    mean, var, count = 0.0, 4.0, 100.0
    for reward, ret, ended in [(1.0, 1.0, False), (1.0, 1.5, True), (2.0, 2.0, False)]:
        delta, total = ret - mean, count + 1
        mean, var, count = mean + delta / total, (var * count + delta**2 * count / total) / total, total
        out = normalizer(np.array([reward]), np.array([ended]))
        assert out[0] == pytest.approx(reward / np.sqrt(var), rel=1e-5)  # about reward / 2
    assert normalizer.returns[0] == 2.0  # the episode ended at the second step: the return restarted
    assert (normalizer.mean, normalizer.var, normalizer.count) == pytest.approx((mean, var, count))


def test_return_normalizer_clips_at_ten():
    normalizer = plr.ReturnNormalizer(num_envs=1, gamma=0.0)
    normalizer.var = 1e-6  # a tiny running std makes any reward huge
    assert normalizer(np.array([5.0]), np.array([False]))[0] == 10.0


def test_feed_forward_minibatches_cover_every_step_once_in_random_order():
    args = plr.paper_args(num_envs=3, num_steps=4, num_minibatches=2)
    np.random.seed(0)
    batches = list(plr.minibatch_rows(False, args, "cpu")[0])
    assert [len(b) for b in batches] == [6, 6]
    rows = torch.cat(batches)
    assert sorted(rows.tolist()) == list(range(12)) and rows.tolist() != list(range(12))


def test_recurrent_minibatches_hold_whole_rollouts_time_major():
    """Copy n's steps are rows t * num_envs + n; a minibatch of copies lists them time-major."""
    np.random.seed(0)
    batches = list(paired.minibatch_rows(True, num_steps=3, n=4, num_minibatches=2, update_epochs=1, device="cpu")[0])
    assert len(batches) == 2
    for rows in batches:
        copies = rows[:2] % 4  # the 2 copies of this minibatch, in its order
        expected = (torch.arange(3).unsqueeze(1) * 4 + copies).reshape(-1)
        assert rows.tolist() == expected.tolist()
    assert sorted(torch.cat(batches).tolist()) == list(range(12))


def test_a_single_minibatch_is_the_whole_batch_as_a_view():
    storage = torch.arange(24.0).view(4, 3, 2)  # [T, N, features]
    for batches in (list(plr.minibatch_rows(True, plr.paper_args(num_envs=3, num_steps=4, num_minibatches=1), "cpu")[0]),
                    list(paired.minibatch_rows(False, num_steps=4, n=3, num_minibatches=1, update_epochs=1, device="cpu")[0])):
        assert len(batches) == 1
        flat = storage.reshape(12, 2)[batches[0]]
        assert torch.equal(flat, storage.reshape(12, 2)) and flat.data_ptr() == storage.data_ptr()


def test_batch_rows_gathers_the_rows_of_any_storage_exactly():
    """Image stacks of bytes go through as 4-byte words (a row of 12 x 4 x 4 bytes); rows of a byte count
    not divisible by 4, and other dtypes, through plain index_select: every row its own bytes, in order."""
    torch.manual_seed(0)
    rows = torch.tensor([5, 0, 5, 11, 3])
    for storage in (torch.randint(0, 256, (4, 3, 12, 4, 4), dtype=torch.uint8),  # CarRacing-like [T, N, C, H, W]
                    torch.randint(0, 256, (4, 3, 5, 5, 3), dtype=torch.uint8),  # the maze's 75-byte views
                    torch.randn(4, 3, 7)):
        flat = storage.reshape((12,) + storage.shape[2:])
        for batch_rows in (plr.batch_rows, paired.batch_rows):
            gathered = batch_rows(storage, rows)
            assert gathered.dtype == storage.dtype and gathered.shape == (5,) + storage.shape[2:]
            assert torch.equal(gathered, torch.stack([flat[r] for r in rows.tolist()]))


def test_value_losses_on_a_worked_example():
    value, old, ret = torch.tensor([1.0, 0.0]), torch.tensor([0.5, 0.0]), torch.tensor([0.0, 3.0])
    args = plr.paper_args(clip_coef=0.2, value_loss="mse")
    assert plr.value_loss_fn(value, old, ret, args).item() == pytest.approx(0.5 * (1.0 + 9.0) / 2)
    args.value_loss = "huber"  # 0.5 x^2 below 1, |x| - 0.5 above
    assert plr.value_loss_fn(value, old, ret, args).item() == pytest.approx((0.5 + 2.5) / 2)
    args.value_loss = "clipped"  # clipped values 0.7 and 0.0: max(1, 0.49) and max(9, 9)
    assert plr.value_loss_fn(value, old, ret, args).item() == pytest.approx(0.5 * (1.0 + 9.0) / 2)
    value = torch.tensor([0.0, 0.0])  # clipped 0.3: max(0, 0.09) makes clipping count
    assert plr.value_loss_fn(value, old, ret, args).item() == pytest.approx(0.5 * (0.09 + 9.0) / 2)
