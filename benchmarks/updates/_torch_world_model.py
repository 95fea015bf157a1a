"""The world-model dynamics update of `hprior_jax.prior.world_model` written out in PyTorch, as
TWM (Robine et al. 2023) runs it: a Python loop over post-LN Transformer-XL layers with
relative-position attention, the z head, the latent + decoded next-state loss, then
clip_grad_norm_ and Adam(weight_decay). It starts from the same weights as a JAX state, so the
benchmark can check that both compute the same loss before it times them.

Benchmarks only: torch is the optional `.[bench]` extra.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F


def _tensor(x, grad: bool) -> torch.Tensor:
    return torch.tensor(np.asarray(x), dtype=torch.float32, requires_grad=grad)


def _mlp(params: dict, grad: bool) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Flax `Dense_i` layers -> [(kernel[in, out], bias)], in order."""
    names = sorted(params, key=lambda n: int(n.split("_")[1]))
    return [(_tensor(params[n]["kernel"], grad), _tensor(params[n]["bias"], grad)) for n in names]


def _run_mlp(layers, x, pre_activation=False, dropout=0.0, training=False):
    if pre_activation:
        x = F.silu(x)
    for kernel, bias in layers[:-1]:
        x = F.dropout(F.silu(x @ kernel + bias), dropout, training)
    kernel, bias = layers[-1]
    return x @ kernel + bias


def rel_shift(x: torch.Tensor) -> torch.Tensor:
    """Transformer-XL's pad-and-reshape shift (same as hprior_jax.networks.transformer_xl)."""
    *lead, tq, tk = x.shape
    x = torch.cat([x.new_zeros(*lead, tq, 1), x], dim=-1)
    return x.view(*lead, tk + 1, tq)[..., 1:, :].reshape(*lead, tq, tk)


class TorchDynamicsUpdate:
    """`step(obs[B, T, ds], act[B, T, da]) -> loss` = one dynamics-model Adam step, dropout on."""

    def __init__(self, state, cfg):
        self.cfg = cfg
        obs_p, dyn_p = state.params.obs["params"], state.params.dyn["params"]
        self.encoder = _mlp(obs_p["encoder"], grad=False)
        self.decoder = _mlp(obs_p["decoder"], grad=False)  # the dynamics loss never updates it
        tr = dyn_p["transformer"]
        lay = tr["layers"]
        self.u, self.v = _tensor(tr["u_bias"], True), _tensor(tr["v_bias"], True)
        self.layers = []
        for i in range(cfg.num_layers):
            pick = lambda *path: _tensor(_get(lay, path)[i], True)
            self.layers.append(dict(
                qkv=pick("self_attn", "qkv_proj", "kernel"), pos=pick("self_attn", "pos_proj", "kernel"),
                out=pick("self_attn", "out_proj", "kernel"),
                ln1=(pick("norm1", "scale"), pick("norm1", "bias")),
                ln2=(pick("norm2", "scale"), pick("norm2", "bias")),
                lin1=(pick("linear1", "kernel"), pick("linear1", "bias")),
                lin2=(pick("linear2", "kernel"), pick("linear2", "bias"))))
        self.z_embed = (_tensor(dyn_p["z_embed"]["kernel"], True), _tensor(dyn_p["z_embed"]["bias"], True))
        self.a_embed = (_tensor(dyn_p["a_embed"]["kernel"], True), _tensor(dyn_p["a_embed"]["bias"], True))
        self.head = _mlp(dyn_p["z_head"], grad=True)
        self.params = [self.u, self.v, *self.z_embed, *self.a_embed,
                       *(t for layer in self.layers for v in layer.values()
                         for t in (v if isinstance(v, tuple) else (v,))),
                       *(t for pair in self.head for t in pair)]
        self.opt = torch.optim.Adam(self.params, lr=cfg.dyn_lr, eps=cfg.dyn_eps,
                                    weight_decay=cfg.dyn_wd)

    def _attention(self, layer, x, pos_enc, mask, training):
        c = self.cfg
        b, t, _ = x.shape
        q, k, val = (x @ layer["qkv"]).split(c.num_heads * c.head_dim, dim=-1)
        q, k, val = (y.view(b, t, c.num_heads, c.head_dim) for y in (q, k, val))
        p = (pos_enc @ layer["pos"]).view(t, c.num_heads, c.head_dim)
        content = torch.einsum("bind,bjnd->bnij", q + self.u, k)
        position = rel_shift(torch.einsum("bind,jnd->bnij", q + self.v, p))
        scale = 1.0 / math.sqrt(c.embed_dim if c.scale_by_model_dim else c.head_dim)
        score = ((content + position) * scale).masked_fill(~mask, float("-inf"))
        attn = F.dropout(torch.softmax(score, dim=-1), c.dropout, training)
        ctx = torch.einsum("bnij,bjnd->bind", attn, val).reshape(b, t, -1)
        return ctx @ layer["out"]

    def loss(self, obs: torch.Tensor, act: torch.Tensor, training: bool = True) -> torch.Tensor:
        c = self.cfg
        drop = lambda y: F.dropout(y, c.dropout, training)
        with torch.no_grad():
            z = _run_mlp(self.encoder, obs)
        b, t, _ = z.shape
        ez = F.silu(z @ self.z_embed[0] + self.z_embed[1])
        ea = F.silu(act @ self.a_embed[0] + self.a_embed[1])
        x = torch.stack([ez, ea], dim=2).reshape(b, 2 * t, c.embed_dim)
        tk = 2 * t
        dist = torch.arange(tk - 1, -1, -1, dtype=torch.float32)
        freq = torch.exp(torch.arange(0, c.embed_dim, 2, dtype=torch.float32)
                         * (-math.log(10000.0) / c.embed_dim))
        ang = dist[:, None] * freq[None, :]
        pos_enc = drop(torch.stack([ang.sin(), ang.cos()], dim=-1).reshape(tk, c.embed_dim))
        gap = torch.arange(tk)[:, None] - torch.arange(tk)[None, :]
        window = 2 * (c.memory_len + 1)
        mask = (gap >= 0) & (gap <= window)
        for layer in self.layers:
            a = self._attention(layer, x, pos_enc, mask, training)
            h = F.layer_norm(x + drop(a), (c.embed_dim,), *layer["ln1"], eps=1e-5)
            ff = drop(drop(F.silu(h @ layer["lin1"][0] + layer["lin1"][1])) @ layer["lin2"][0]
                      + layer["lin2"][1])
            x = F.layer_norm(h + ff, (c.embed_dim,), *layer["ln2"], eps=1e-5)
        z_pred = _run_mlp(self.head, x[:, 1::2], pre_activation=True, dropout=c.dropout,
                          training=training)[:, :-1]
        with torch.no_grad():
            z_next = _run_mlp(self.encoder, obs[:, 1:])
        latent = 0.5 * ((z_pred - z_next) ** 2).sum(-1).mean()
        next_obs = 0.5 * ((_run_mlp(self.decoder, z_pred) - obs[:, 1:]) ** 2).sum(-1).mean()
        return c.latent_coef * latent + c.next_obs_coef * next_obs

    def grad_norm(self, obs, act) -> float:
        """Global gradient norm of the deterministic loss (the parity check; no step taken)."""
        self.opt.zero_grad()
        self.loss(obs, act, training=False).backward()
        return float(torch.sqrt(sum((p.grad ** 2).sum() for p in self.params)))

    def step(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        self.opt.zero_grad()
        loss = self.loss(obs, act)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.params, self.cfg.dyn_grad_clip)
        self.opt.step()
        return loss.detach()


def _get(tree: dict, path: tuple[str, ...]):
    for key in path:
        tree = tree[key]
    return tree
