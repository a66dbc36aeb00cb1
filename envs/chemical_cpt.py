"""The Chemical environment's conditional probability tables: one fixed random MLP per object.

Object k's table reads every object's one-hot colour (``N * num_colors`` inputs) multiplied by a
mask keeping only k's parents' slots, then ``4N`` ReLU units, then ``num_colors`` logits; the new
colour is *sampled* from their softmax. Weights are orthogonal with gain 3, biases U(-0.2, 0.2),
drawn from ``numpy.random.Generator(PCG64(seed))`` object by object, so they depend only on
(N, num_colors, seed): never on the graph, the worker or the episode seed.

Speed: a table with at most ``max_table_rows`` parent configurations is evaluated once, for every
configuration, into a cumulative-probability array (an exact cache of the MLP). A larger one is
evaluated on the fly; for single states its first layer (a sum of one weight row per parent) is
read from per-chunk partial sums over at most ``CHUNK_ROWS`` configurations of a few parents.
Either way a colour is drawn by inverse CDF from one uniform: the number of cumulative
probabilities ``<= u`` (the last set to exactly 1).
"""
from __future__ import annotations

import math
from bisect import bisect_right

import numpy as np

from envs.graphs import ObjectDAG

INIT_GAIN = 3.0
BIAS_RANGE = 0.2
HIDDEN_PER_OBJECT = 4
MAX_TABLE_ROWS = 5**7
"""Tabulate a CPT with at most this many parent configurations (5 colours, 7 parents: 3 MiB)."""
CHUNK_ROWS = 5**5
"""Most configurations per partial first-layer sum of an untabulated CPT."""


def orthogonal(rng: np.random.Generator, rows: int, cols: int, gain: float) -> np.ndarray:
    """A ``rows x cols`` matrix with orthonormal rows or columns times ``gain`` (torch's
    ``nn.init.orthogonal_`` algorithm: QR of a Gaussian matrix, signs fixed by R's diagonal)."""
    flat = rng.standard_normal((rows, cols))
    if rows < cols:
        flat = flat.T
    q, r = np.linalg.qr(flat)
    q *= np.sign(np.diag(r))
    if rows < cols:
        q = q.T
    return gain * q


class ChemicalCPT:
    """The fixed conditional probability tables of one object DAG, and the intervention dynamics."""

    def __init__(self, dag: ObjectDAG, num_colors: int, seed: int, max_table_rows: int = MAX_TABLE_ROWS) -> None:
        n, c = dag.num_objects, num_colors
        self.num_objects, self.num_colors = n, c
        self._parents = tuple(dag.parents(k) for k in range(n))
        self._w1, self._w2 = _init_weights(n, c, seed, self._parents)
        self._w2_of = tuple(self._w2)
        topo = dag.topological_order()
        self._resample_order = tuple(tuple(k for k in topo if k in dag.descendants(i)) for i in range(n))
        self._powers = tuple(c ** np.arange(len(p) - 1, -1, -1) for p in self._parents)
        self._eye = np.eye(c)
        tabulate = [bool(p) and c ** len(p) <= max_table_rows for p in self._parents]  # roots: never sampled
        self._tables = tuple(self._tabulate(k) if t else None for k, t in enumerate(tabulate))
        self._chunks = tuple(
            self._first_layer_chunks(k) if p and not t else () for k, (p, t) in enumerate(zip(self._parents, tabulate))
        )

    def parents(self, k: int) -> tuple[int, ...]:
        """The objects whose colours object ``k``'s table reads."""
        return self._parents[k]

    def resample_order(self, target: int) -> tuple[int, ...]:
        """The objects re-sampled after an action on ``target``, in the order they are re-sampled
        (topological, so every re-sampled parent comes before its children)."""
        return self._resample_order[target]

    def probabilities(self, colors: np.ndarray, k: int) -> np.ndarray:
        """Object ``k``'s colour distribution given ``colors`` (int ``[B, N]``): float ``[B, C]``,
        computed by the literal masked MLP (never from the caches)."""
        logits = self._logits(colors, k)
        p = np.exp(logits - logits.max(axis=1, keepdims=True))
        return p / p.sum(axis=1, keepdims=True)

    def intervene(self, colors: np.ndarray, target: int, color: int, rng: np.random.Generator) -> None:
        """Set ``target`` to ``color`` in every row of ``colors`` (int ``[B, N]``, updated in place),
        then re-sample its descendants, in order, from their parents' newest colours. Draws one
        ``rng.random((B, d))`` for the ``d`` re-sampled objects and nothing else."""
        colors[:, target] = color
        order = self._resample_order[target]
        if order:
            u = rng.random((len(colors), len(order)))
            for k, uk in zip(order, u.T):
                colors[:, k] = self._sample(colors, k, uk)

    def intervene_one(self, colors: list[int], target: int, color: int, rng: np.random.Generator) -> None:
        """:meth:`intervene` on one state held as a list (updated in place), in scalar arithmetic:
        the same draws and the same colours as a batch of one (for untabulated objects, up to
        rounding: a draw could differ only if its uniform fell within ~1e-16 of a boundary)."""
        colors[target] = color
        order = self._resample_order[target]
        if not order:
            return
        for k, uk in zip(order, rng.random((1, len(order)))[0].tolist()):
            table = self._tables[k]
            if table is not None:
                colors[k] = bisect_right(table[self._key(colors, self._parents[k])], uk)
                continue
            h = self._first_layer_one(colors, k)
            np.maximum(h, 0.0, out=h)
            colors[k] = _inverse_cdf(np.dot(h, self._w2_of[k]).tolist(), uk)

    def _key(self, colors: list[int], parents: tuple[int, ...]) -> int:
        key, c = 0, self.num_colors
        for p in parents:
            key = key * c + colors[p]
        return key

    def _first_layer_one(self, colors: list[int], k: int) -> np.ndarray:
        chunks = self._chunks[k]
        parents, partial_sums = chunks[0]
        h = partial_sums[self._key(colors, parents)].copy()
        for parents, partial_sums in chunks[1:]:
            h += partial_sums[self._key(colors, parents)]
        return h

    def _first_layer_chunks(self, k: int) -> tuple[tuple[tuple[int, ...], np.ndarray], ...]:
        """Object ``k``'s parents in chunks, each with the sum of its weight rows for every
        configuration (the first chunk also holding the bias), same row order as :meth:`_tabulate`."""
        c, parents = self.num_colors, self._parents[k]
        per_chunk = 1
        while c ** (per_chunk + 1) <= CHUNK_ROWS:
            per_chunk += 1
        chunks = [parents[i:i + per_chunk] for i in range(0, len(parents), per_chunk)]
        out = []
        for i, chunk in enumerate(chunks):
            configs = np.indices((c,) * len(chunk)).reshape(len(chunk), -1).T
            rows = self._w1[k][np.asarray(chunk, dtype=np.int64) * c + configs].sum(axis=1)
            out.append((chunk, rows + self._w1[k][-1] if i == 0 else rows))
        return tuple(out)

    def _sample(self, colors: np.ndarray, k: int, u: np.ndarray) -> np.ndarray:
        table = self._tables[k]
        if table is None:
            cum = self._cumulative(colors, k)
        else:
            cum = table[colors[:, self._parents[k]] @ self._powers[k]]
        return (cum <= u[:, None]).sum(axis=1)

    def _tabulate(self, k: int) -> np.ndarray:
        """Cumulative probabilities for every parent configuration, row = base-C number of the
        parents' colours (first parent most significant)."""
        parents, c = self._parents[k], self.num_colors
        configs = np.indices((c,) * len(parents)).reshape(len(parents), -1).T
        colors = np.zeros((len(configs), self.num_objects), dtype=np.int64)
        colors[:, parents] = configs
        return self._cumulative(colors, k)

    def _cumulative(self, colors: np.ndarray, k: int) -> np.ndarray:
        cum = np.minimum(np.cumsum(self.probabilities(colors, k), axis=1), 1.0)
        cum[:, -1] = 1.0
        return cum

    def _logits(self, colors: np.ndarray, k: int) -> np.ndarray:
        b, n = colors.shape
        x = np.empty((b, n * self.num_colors + 1))
        x[:, :-1] = self._eye[colors].reshape(b, -1)
        x[:, -1] = 1.0
        h = x @ self._w1[k]
        np.maximum(h, 0.0, out=h)
        return h @ self._w2[k]


def _init_weights(
    n: int, c: int, seed: int, parents: tuple[tuple[int, ...], ...]
) -> tuple[np.ndarray, np.ndarray]:
    """Per object: first layer ``[N*C + 1, 4N + 1]`` masked to the parents' slots, with its bias as
    the last input row and a constant unit as the last hidden column; second layer
    ``[4N + 1, C]`` whose last row (read by the constant unit) is its bias."""
    rng = np.random.Generator(np.random.PCG64(seed))
    hidden = HIDDEN_PER_OBJECT * n
    w1 = np.zeros((n, n * c + 1, hidden + 1))
    w2 = np.zeros((n, hidden + 1, c))
    for k in range(n):
        mask = np.zeros((n, c))
        mask[list(parents[k])] = 1.0
        w1[k, :-1, :-1] = orthogonal(rng, hidden, n * c, INIT_GAIN).T * mask.reshape(-1, 1)
        w1[k, -1, :-1] = rng.uniform(-BIAS_RANGE, BIAS_RANGE, hidden)
        w1[k, -1, -1] = 1.0
        w2[k, :-1] = orthogonal(rng, c, hidden, INIT_GAIN).T
        w2[k, -1] = rng.uniform(-BIAS_RANGE, BIAS_RANGE, c)
    return w1, w2


def _inverse_cdf(logits: list[float], u: float) -> int:
    """The number of cumulative softmax probabilities ``<= u`` (the last counted as 1), in scalar
    arithmetic: equal to the batched sampler up to floating-point rounding."""
    top = max(logits)
    weights = [math.exp(v - top) for v in logits]
    threshold = u * sum(weights)
    total = 0.0
    for i, w in enumerate(weights[:-1]):
        total += w
        if total > threshold:
            return i
    return len(weights) - 1
