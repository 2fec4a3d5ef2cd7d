"""Codes for computing with stragglers (issue 30), over the reals, pure numpy.

MDS-coded matrix multiplication (Lee et al., "Speeding Up Distributed Machine Learning Using Codes", IEEE Trans.
Inf. Theory 2018): A's rows in k blocks, encoded into n coded blocks by a generator G (n x k); any k results
G_S (A B) decode by solving with G_S. The generator here is systematic, G = [I_k; P], the first k workers holding
A's own blocks (with nobody missing the decode is a copy), and P a Cauchy matrix, P_ij = 1 / (x_i - y_j), on
Chebyshev nodes of [-1, 1] shared out between the x (parity) and y (data) so that they interleave, each row scaled
to a largest entry of 1. Every square submatrix of a Cauchy matrix with distinct nodes is nonsingular, so every
k x k submatrix of G is (an MDS code exactly, not with probability 1 as with random parity: Gaussian parity drew a
1e-3 entry here and a worst condition number of 1.2e3 already at n = 3). Not a Vandermonde matrix: over the reals
its condition number grows exponentially with k (Gautschi). Worst condition numbers of this construction over
every k-subset, measured (the largest over k, for each n): n = 3: 3; 4: 6; 6: 61; 8: 247; 10: 2,978. The worst is
computed when a code is made, and a code worse than MAX_CONDITION is refused.

Gradient coding (Tandon, Lei, Dimakis and Karampatziakis, "Gradient Coding", ICML 2017): the data in n shards, worker
i holds shards i..i+s (mod n) and sends one combination sum_j B[i, j] g_j of their gradients; from any n - s
workers F the master finds a with a B_F = 1 and gets the full gradient sum_j g_j = sum_{i in F} a_i c_i. B is the
paper's cyclic-support construction (its Algorithm 2): H (s x n) random with H 1 = 0, each row of B the null
vector of H restricted to that row's support, scaled to 1 on the diagonal; every row lies in null(H), which holds
the all-ones vector and which any n - s rows span.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

MAX_CONDITION = 1e8  # a decoding matrix worse than this loses more than half of float64's 16 digits: refused
EXACT_SUBSETS = 20_000  # up to this many k-subsets the worst condition number is computed over all of them


class CodeError(ValueError):
    """A code that cannot be made or decoded (the caller turns it into BadInput, or a record and a fallback)."""


def mds_generator(n: int, k: int) -> np.ndarray:
    """Systematic real generator (n x k): the identity on top, Cauchy parity rows below (module docstring)."""
    if not 1 <= k <= n:
        raise CodeError(f"an (n={n}, k={k}) code needs 1 <= k <= n: k is how many of the n workers' results decode")
    nodes = np.sort(np.cos(np.pi * (2 * np.arange(n) + 1) / (2 * n)))
    data = np.round(np.linspace(0, n - 1, k)).astype(int) if k > 1 else np.array([n // 2])
    parity = np.setdiff1d(np.arange(n), data)
    cauchy = 1.0 / (nodes[parity][:, None] - nodes[data][None, :])
    return np.vstack([np.eye(k), cauchy / np.abs(cauchy).max(axis=1, keepdims=True)])


def worst_condition(generator: np.ndarray, seed: int = 0) -> float:
    """The largest 2-norm condition number of any k x k row submatrix (over all of them up to EXACT_SUBSETS,
    else over that many drawn at random: then a lower bound, which is said by the caller)."""
    n, k = generator.shape
    if math.comb(n, k) <= EXACT_SUBSETS:
        subsets = itertools.combinations(range(n), k)
    else:
        rng = np.random.default_rng(seed)
        subsets = (sorted(rng.choice(n, k, replace=False)) for _ in range(EXACT_SUBSETS))
    return max(float(np.linalg.cond(generator[list(s)])) for s in subsets)


def check_mds(n: int, k: int, rows: int, advice: str) -> None:
    """An (n, k) code over `rows` rows of A that can be made and decoded: k within the rows, and every k of its n
    blocks decodable within MAX_CONDITION (else CodeError ending in `advice`)."""
    if k > rows:
        raise CodeError(f"--code-k {k}: A has only {rows} rows to cut into k blocks")
    worst = worst_condition(mds_generator(n, k))
    if not worst <= MAX_CONDITION:
        raise CodeError(f"the ({n}, {k}) code has a decoding matrix of condition number {worst:.3g} "
                        f"(> {MAX_CONDITION:g}): {advice}")


def row_blocks(a: np.ndarray, k: int) -> np.ndarray:
    """A's rows as k equal blocks (k x ceil(m / k) x n), the last padded with zero rows."""
    rows = -(-len(a) // k)
    padded = np.zeros((k * rows, a.shape[1]))
    padded[:len(a)] = a
    return padded.reshape(k, rows, a.shape[1])


def encode(generator: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """Coded blocks (n x rows x cols) from the k data blocks (k x rows x cols)."""
    return np.tensordot(generator, blocks, axes=1)


def mds_decode(generator: np.ndarray, used: list[int], results: np.ndarray) -> tuple[np.ndarray, float]:
    """The k data blocks' products from the results of k coded blocks (`used`: their rows of G, in the order of
    `results`, k x ...), and the condition number of the system solved. A systematic code's first k rows alone
    decode by copying."""
    k = generator.shape[1]
    if len(used) != k:
        raise CodeError(f"decoding needs exactly k={k} results, got {len(used)}")
    if sorted(used) == list(range(k)):
        order = np.argsort(used)
        return results[order], 1.0
    system = generator[used]
    condition = float(np.linalg.cond(system))
    if not condition <= MAX_CONDITION:
        raise CodeError(f"the decoding matrix of workers {used} has condition number {condition:.3g} "
                        f"(> {MAX_CONDITION:g})")
    flat = results.reshape(k, -1)
    return np.linalg.solve(system, flat).reshape(results.shape), condition


def gradient_code(n: int, s: int, seed: int = 0) -> np.ndarray:
    """Tandon et al.'s cyclic-support B (n x n): row i is nonzero on columns i..i+s (mod n)."""
    if not 0 <= s < n:
        raise CodeError(f"gradient coding with n={n} workers tolerates 0 <= s < n stragglers, got s={s}")
    if s == 0:
        return np.eye(n)
    rng = np.random.default_rng(seed)
    h = rng.standard_normal((s, n))
    h[:, -1] = -h[:, :-1].sum(axis=1)  # H 1 = 0: the all-ones vector lies in null(H)
    b = np.zeros((n, n))
    for i in range(n):
        support = shards_of(i, n, s)
        null = np.linalg.svd(h[:, support])[2][-1]  # H_S (s x (s+1)) has a one-dimensional null space
        if abs(null[0]) < 1e-12:
            raise CodeError(f"gradient code row {i} has no weight on its own shard (seed {seed}): use another seed")
        b[i, support] = null / null[0]
    return b


def shards_of(worker: int, n: int, s: int) -> list[int]:
    """The shards worker `worker` (0-based) holds under the cyclic code: worker..worker+s (mod n)."""
    return [(worker + j) % n for j in range(s + 1)]


def gradient_decoder(b: np.ndarray, used: list[int]) -> tuple[np.ndarray, float]:
    """a with a B[used] = 1 (least squares on the transposed system) and the residual's largest entry."""
    rows = b[used]
    a, *_ = np.linalg.lstsq(rows.T, np.ones(b.shape[1]), rcond=None)
    residual = float(np.abs(a @ rows - 1.0).max())
    if residual > 1e-8:
        raise CodeError(f"workers {used} cannot give the full gradient (residual {residual:.3g}): need any "
                        f"{b.shape[0] - _tolerated(b)} of the {b.shape[0]} workers")
    return a, residual


def _tolerated(b: np.ndarray) -> int:
    """s of a cyclic-support B: its row's nonzeros minus one."""
    return int(np.count_nonzero(np.abs(b[0]) > 0)) - 1
