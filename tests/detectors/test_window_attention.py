"""Windowed cross-attention (each query attends to the W x W tokens around its anchor):
windows placed and clamped on the grid, weights a proper map over every token, the whole-grid
window equal to dense multi-head attention, the folded projections equal to projecting every
gathered key and value, both kernels equal, gradients reaching the map."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from detectors.model import Detector
from detectors.model.bev import BEVGrid
from detectors.model.window_attention import WindowCrossAttention
from detectors.sim import make_frame

GRID = BEVGrid(size=16, cell=0.8)


def _inputs(b: int = 2, q: int = 5, d: int = 8, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    t = GRID.size ** 2
    anchors = (torch.rand(b, q, 2, generator=g) - 0.5) * 2 * GRID.half_extent
    return (torch.randn(b, q, d, generator=g), torch.randn(b, q, d, generator=g),
            torch.randn(b, t, d, generator=g), torch.randn(1, t, d, generator=g), anchors)


def test_windows_sit_around_the_anchor_and_stay_inside_the_grid():
    attn = WindowCrossAttention(8, 2, 4, GRID)
    centres = GRID.centres()
    # an anchor at the centre of cell (row 7, col 9): its 4 x 4 window covers rows 6..9 and
    # columns 8..11 (the anchor's cell and the one after it are the middle two)
    anchor = centres[7 * 16 + 9] + 0.1
    index = attn.window_index(anchor.view(1, 1, 2))[0, 0]
    rows, cols = index // 16, index % 16
    assert sorted(set(rows.tolist())) == [6, 7, 8, 9]
    assert sorted(set(cols.tolist())) == [8, 9, 10, 11]
    corner = attn.window_index(torch.tensor([[[-100.0, 100.0]]]))[0, 0]
    assert sorted(set((corner // 16).tolist())) == [12, 13, 14, 15]   # clamped at the top
    assert sorted(set((corner % 16).tolist())) == [0, 1, 2, 3]        # and at the left
    with pytest.raises(ValueError, match="attn_window"):
        WindowCrossAttention(8, 2, 17, GRID)


def test_weights_are_a_map_over_every_token_zero_outside_the_window():
    torch.manual_seed(0)
    attn = WindowCrossAttention(8, 2, 4, GRID)
    query, pos, memory, memory_pos, anchors = _inputs()
    out, weights = attn(query, pos, memory, memory_pos, anchors)
    assert out.shape == (2, 5, 8) and weights.shape == (2, 5, 256)
    torch.testing.assert_close(weights.sum(-1), torch.ones(2, 5))
    inside = torch.zeros_like(weights, dtype=torch.bool).scatter_(
        2, attn.window_index(anchors), True)
    assert (weights[~inside] == 0).all() and (weights[inside] > 0).all()
    # the fused kernel (training, no weights) gives the same output
    fused, none = attn(query, pos, memory, memory_pos, anchors, need_weights=False)
    assert none is None
    torch.testing.assert_close(fused, out, rtol=1e-5, atol=1e-6)


def test_a_whole_grid_window_is_dense_multi_head_attention():
    torch.manual_seed(0)
    attn = WindowCrossAttention(8, 2, 16, GRID)
    dense = nn.MultiheadAttention(8, 2, batch_first=True)
    with torch.no_grad():
        dense.in_proj_weight.copy_(torch.cat([attn.q_proj.weight, attn.k_proj.weight,
                                              attn.v_proj.weight]))
        dense.in_proj_bias.copy_(torch.cat([attn.q_proj.bias, attn.k_proj.bias,
                                            attn.v_proj.bias]))
        dense.out_proj.weight.copy_(attn.out_proj.weight)
        dense.out_proj.bias.copy_(attn.out_proj.bias)
    query, pos, memory, memory_pos, anchors = _inputs()
    out, weights = attn(query, pos, memory, memory_pos, anchors)
    want, want_w = dense(query + pos, memory + memory_pos, memory, average_attn_weights=True)
    torch.testing.assert_close(out, want, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(weights, want_w, rtol=1e-5, atol=1e-7)


def _projected_reference(attn: WindowCrossAttention, query, pos, memory, memory_pos, anchors):
    """The textbook computation: gather each window, project its keys and values, attend."""
    b, q, d = query.shape
    h, dh = attn.n_heads, d // attn.n_heads
    index = attn.window_index(anchors)                                   # [B, Q, K]
    rows = torch.stack([memory[i][index[i]] for i in range(b)])          # [B, Q, K, D]
    keys = attn.k_proj(rows + memory_pos[0][index]).view(b, q, -1, h, dh)
    vals = attn.v_proj(rows).view(b, q, -1, h, dh)
    qh = attn.q_proj(query + pos).view(b, q, h, dh)
    w = (torch.einsum("bqhe,bqkhe->bqhk", qh, keys) / dh ** 0.5).softmax(-1)
    out = attn.out_proj(torch.einsum("bqhk,bqkhe->bqhe", w, vals).reshape(b, q, d))
    dense = torch.zeros(b, q, memory.shape[1]).scatter_(2, index, w.mean(2))
    return out, dense


def test_folded_projections_equal_projecting_every_gathered_key_and_value():
    torch.manual_seed(1)
    attn = WindowCrossAttention(8, 2, 5, GRID)
    with torch.no_grad():           # biases that matter if a fold dropped them
        for lin in (attn.q_proj, attn.k_proj, attn.v_proj, attn.out_proj):
            lin.bias.normal_()
    query, pos, memory, memory_pos, anchors = _inputs(b=3, q=7, seed=2)
    out, weights = attn(query, pos, memory, memory_pos, anchors)
    want, want_w = _projected_reference(attn, query, pos, memory, memory_pos, anchors)
    torch.testing.assert_close(out, want, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(weights, want_w, rtol=1e-5, atol=1e-7)
    # the keys summed once by the caller (the detector's path) give the same
    keyed, _ = attn(query, pos, memory, memory_pos, anchors,
                    memory_keys=memory + memory_pos)
    torch.testing.assert_close(keyed, out, rtol=0, atol=0)
    # and the same gradients (what training sees); k_proj's bias shifts every logit of a
    # row alike, so its true gradient is 0 and the fold leaves it out
    tensors = [query, pos, memory, memory_pos]
    params = [attn.q_proj.weight, attn.k_proj.weight, attn.v_proj.weight, attn.v_proj.bias]
    probe = torch.randn(out.shape)
    grads = []
    for fn in (lambda *a: attn(*a)[0], lambda *a: _projected_reference(attn, *a)[0]):
        inputs = [x.detach().clone().requires_grad_(True) for x in tensors]
        result = fn(*inputs, anchors)
        grads.append(torch.autograd.grad((result * probe).sum(), inputs + params))
    for got, ref in zip(*grads, strict=True):
        torch.testing.assert_close(got, ref, rtol=1e-4, atol=1e-5)


def test_gradients_reach_the_token_map_inside_the_windows_only():
    attn = WindowCrossAttention(8, 2, 3, GRID)
    query, pos, memory, memory_pos, anchors = _inputs(b=1, q=1)
    memory.requires_grad_(True)
    out, _ = attn(query, pos, memory, memory_pos, anchors, need_weights=False)
    out.sum().backward()
    touched = memory.grad.abs().sum(-1)[0] > 0
    assert touched.sum() == 9
    assert set(np.flatnonzero(touched.numpy())) == set(attn.window_index(anchors)[0, 0].tolist())


def test_a_windowed_detector_gives_attention_over_the_fine_grid(tiny_config):
    torch.manual_seed(0)
    cfg = tiny_config(head="group", token_stride=1, attn_window=6)
    model = Detector(cfg).eval()
    points = [torch.from_numpy(np.array(make_frame(s, "lidar").sensor_frame.points,
                                        dtype=np.float32)) for s in (3, 4)]
    with torch.no_grad():
        out = model(points)
    t = cfg.grid_size ** 2
    assert out["attention"].shape == (cfg.n_layers, 2, cfg.n_queries, t)
    assert model.token_centres.shape == (t, 2)
    torch.testing.assert_close(out["attention"].sum(-1), torch.ones(cfg.n_layers, 2,
                                                                    cfg.n_queries))
    assert ((out["attention"] > 0).sum(-1) <= 36).all()
    # the detector's one [L, B, Q, T] buffer holds what each layer computes on its own
    with torch.no_grad():
        enc = model.encode(points)
        query, anchors = enc.init.content, out["anchors"]
        for i, layer in enumerate(model.layers):
            alone = layer(query, model.position(anchors[i]), enc.memory, enc.memory_pos,
                          anchors=anchors[i])
            torch.testing.assert_close(alone.attention, out["attention"][i], rtol=0, atol=0)
            query = alone.query
    with pytest.raises(ValueError, match="attn_window"):
        tiny_config(token_stride=1, attn_window=65)
    # old configurations (no attn_window) load as dense attention
    legacy = {k: v for k, v in cfg.to_dict().items() if k != "attn_window"}
    assert type(cfg).from_dict(legacy).attn_window == 0
