"""DETR-style transformer layers: positions are added to queries and keys, never to values."""
from __future__ import annotations

import torch
from torch import Tensor, nn


class FeedForward(nn.Module):
    def __init__(self, dim: int, hidden: int, dropout: float) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(dim, hidden), nn.ReLU(inplace=True),
                                 nn.Dropout(dropout), nn.Linear(hidden, dim))

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x)


class EncoderLayer(nn.Module):
    """Post-norm self-attention + feed-forward over (B, S, d) tokens."""

    def __init__(self, dim: int, heads: int, hidden: int, dropout: float = 0.0) -> None:
        super().__init__()
        self.attn = nn.MultiheadAttention(dim, heads, dropout=dropout, batch_first=True)
        self.ffn = FeedForward(dim, hidden, dropout)
        self.norm1, self.norm2 = nn.LayerNorm(dim), nn.LayerNorm(dim)
        self.drop = nn.Dropout(dropout)

    def forward(self, src: Tensor, pos: Tensor) -> Tensor:
        qk = src + pos
        src = self.norm1(src + self.drop(self.attn(qk, qk, src, need_weights=False)[0]))
        return self.norm2(src + self.drop(self.ffn(src)))


class DecoderLayer(nn.Module):
    """Query self-attention, cross-attention to the encoded map, feed-forward (post-norm)."""

    def __init__(self, dim: int, heads: int, hidden: int, dropout: float = 0.0) -> None:
        super().__init__()
        self.self_attn = nn.MultiheadAttention(dim, heads, dropout=dropout, batch_first=True)
        self.cross_attn = nn.MultiheadAttention(dim, heads, dropout=dropout, batch_first=True)
        self.ffn = FeedForward(dim, hidden, dropout)
        self.norm1, self.norm2, self.norm3 = (nn.LayerNorm(dim) for _ in range(3))
        self.drop = nn.Dropout(dropout)

    def forward(self, tgt: Tensor, memory: Tensor, pos: Tensor, query_pos: Tensor) -> Tensor:
        q = tgt + query_pos
        tgt = self.norm1(tgt + self.drop(self.self_attn(q, q, tgt, need_weights=False)[0]))
        attended = self.cross_attn(tgt + query_pos, memory + pos, memory, need_weights=False)[0]
        tgt = self.norm2(tgt + self.drop(attended))
        return self.norm3(tgt + self.drop(self.ffn(tgt)))


class Transformer(nn.Module):
    """Encoder over map tokens, decoder over N learned queries; returns every decoder layer."""

    def __init__(self, dim: int, heads: int, hidden: int, enc_layers: int, dec_layers: int,
                 dropout: float = 0.0) -> None:
        super().__init__()
        self.encoder = nn.ModuleList(EncoderLayer(dim, heads, hidden, dropout)
                                     for _ in range(enc_layers))
        self.decoder = nn.ModuleList(DecoderLayer(dim, heads, hidden, dropout)
                                     for _ in range(dec_layers))

    def forward(self, src: Tensor, pos: Tensor, query_pos: Tensor) -> Tensor:
        """src (B, S, d), pos (S, d), query_pos (N, d) -> (layers, B, N, d)."""
        for layer in self.encoder:
            src = layer(src, pos)
        query_pos = query_pos.unsqueeze(0).expand(src.shape[0], -1, -1)
        tgt, outputs = torch.zeros_like(query_pos), []
        for layer in self.decoder:
            tgt = layer(tgt, src, pos, query_pos)
            outputs.append(tgt)
        return torch.stack(outputs)
