"""Combination of cues (Fontmarty §3.2.4, Brubaker eq. 10) and construction by name.

Example::

    from torchpf.likelihoods import make_likelihood
    lik = make_likelihood(skel, cameras, {"silhouette": 1.0, "pointcloud": 0.5})   # a ProductLikelihood
    logw = lik(particles, frame)                                                   # (..., N)
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence

import torch
from torch import nn

from torchpf.filters.weights import ess, survival_fraction, temper
from torchpf.likelihoods.base import LIKELIHOODS, Body, Likelihood

__all__ = ["ProductLikelihood", "TemperedLikelihood", "calibrate_temperature", "make_likelihood"]


class ProductLikelihood(nn.Module):
    """Product of independent cues (Fontmarty §3.2.4, Brubaker eq. 10) with per-term exponents:
    ``log p = sum_k w_k log p_k(theta, obs)``. An annealing exponent ``beta`` (APF layer) multiplies the
    whole sum, so it composes: ``beta * lik(theta, obs)``.

    Args:
        terms: name -> likelihood module (or a sequence, named "0", "1", ...).
        weights: name -> exponent (default 1 for each).
        learnable: ``True`` makes the exponents an ``nn.Parameter`` ``term_weights`` (K,) (in the terms'
            order), else it is a buffer; :attr:`weights` reads them as a name -> 0-dim tensor mapping.

    obs: a :class:`~torchpf.observations.Frame` (or a dict of the same fields); each term picks its field
    and a missing field contributes 0. The body (forward kinematics) is computed once per call and handed to
    every term (:meth:`Likelihood.log_likelihood_body`).
    """

    def __init__(
        self, terms, weights: Mapping[str, float] | Sequence[float] | None = None, *, learnable: bool = False
    ):
        super().__init__()
        if not isinstance(terms, Mapping):
            terms = {str(i): t for i, t in enumerate(terms)}
        self.terms = nn.ModuleDict(terms)
        if weights is None:
            weights = {k: 1.0 for k in terms}
        elif not isinstance(weights, Mapping):
            weights = dict(zip(terms, weights, strict=True))
        unknown = set(weights) - set(terms)
        if unknown:
            raise ValueError(f"weights for unknown terms {sorted(unknown)}")
        values = torch.tensor([float(weights.get(k, 1.0)) for k in terms], dtype=torch.float64)
        if learnable:
            self.term_weights = nn.Parameter(values)
        else:
            self.register_buffer("term_weights", values)
        # terms with a fixed exponent of 0 are not evaluated at all (decided here: no host sync per call)
        self._active = [k for k, w in zip(terms, values.tolist(), strict=True) if learnable or w != 0]

    @property
    def weights(self) -> dict[str, torch.Tensor]:
        """Name -> exponent ``w_k`` (0-dim views of :attr:`term_weights`)."""
        return dict(zip(self.terms, self.term_weights.unbind(), strict=True))

    def _values(self, theta: torch.Tensor, obs, names) -> Iterator[tuple[str, torch.Tensor]]:
        """(name, unweighted log-likelihood (..., N)) of the terms ``names``: the body of each skeleton is
        computed once, on first need, and handed to every :class:`Likelihood` term; other modules are
        called as ``term(theta, obs)``."""
        bodies: dict[int, Body] = {}
        for k in names:
            term = self.terms[k]
            if not isinstance(term, Likelihood):
                yield k, term(theta, obs)
            elif term.select(obs) is None:  # no data for this cue: no FK for it either
                yield k, theta.new_zeros(theta.shape[:-1])
            else:
                key = id(term.skeleton)
                if key not in bodies:
                    bodies[key] = term.body(theta)
                yield k, term.log_likelihood_body(bodies[key], obs)

    def components(self, theta: torch.Tensor, obs) -> dict[str, torch.Tensor]:
        """Unweighted log-likelihood (..., N) of each term, for diagnostics and tuning."""
        return dict(self._values(theta, obs, list(self.terms)))

    def forward(self, theta: torch.Tensor, obs) -> torch.Tensor:
        """(..., N, D), Frame -> (..., N) weighted sum of the terms' log-likelihoods."""
        total = theta.new_zeros(theta.shape[:-1])
        weights = self.weights
        for k, value in self._values(theta, obs, self._active):
            total = total + weights[k].to(value) * value
        return total


class TemperedLikelihood(nn.Module):
    """``beta * log p(z | theta)``: a likelihood raised to a power ``beta`` (a temperature ``1 / beta``).

    A likelihood's sharpness depends on the masks' resolution and noise as much as on the pose; ``beta``
    rescales it so that the importance weights are neither degenerate (ESS ~ 1) nor flat (ESS ~ N). It is the
    annealing exponent of Brubaker eq. 20 held fixed for a whole sequence; :func:`calibrate_temperature` sets
    it from the first frame. ``beta`` is a buffer (moves with ``.to``; ``(...)``-shaped for one value per
    sequence or a scalar).
    """

    def __init__(self, likelihood: nn.Module, beta: float | torch.Tensor = 1.0):
        super().__init__()
        self.likelihood = likelihood
        self.register_buffer("beta", torch.as_tensor(beta, dtype=torch.float64).clone())

    def forward(self, theta: torch.Tensor, obs) -> torch.Tensor:
        """(..., N, D), obs -> (..., N): the wrapped log-likelihood times ``beta`` (``-inf`` stays)."""
        value = self.likelihood(theta, obs)
        beta = self.beta.to(value)
        return temper(beta.expand(value.shape[:-1]), value)

    def extra_repr(self) -> str:
        return f"beta={self.beta.tolist()}"


def calibrate_temperature(
    likelihood: nn.Module,
    theta: torch.Tensor,
    obs,
    survival_rate: float = 0.2,
    bounds: tuple[float, float] = (1e-3, 1e3),
    iterations: int = 40,
) -> torch.Tensor:
    """The exponent ``beta (...)`` at which ``beta * log p(obs | theta)`` over the particles
    ``theta (..., N, D)`` has ``ESS / N = survival_rate`` (Deutscher's survival rate; bisection on
    ``log beta`` within ``bounds``, batched over sequences, no host sync).

    The ESS of ``beta * l`` falls as ``beta`` grows; where even ``bounds[0]`` leaves fewer survivors the lower
    bound is returned, where even ``bounds[1]`` leaves more (an almost flat likelihood) the upper bound. A
    sequence whose log-likelihoods are all ``-inf``/NaN gets 1.
    """
    with torch.no_grad():
        energy = likelihood(theta, obs).to(torch.float64)
        lo = torch.full(energy.shape[:-1], math.log(bounds[0]), dtype=torch.float64, device=energy.device)
        hi = torch.full_like(lo, math.log(bounds[1]))
        for _ in range(iterations):
            mid = 0.5 * (lo + hi)
            enough = survival_fraction(temper(mid.exp(), energy)) >= survival_rate
            lo, hi = torch.where(enough, mid, lo), torch.where(enough, hi, mid)
        beta = (0.5 * (lo + hi)).exp()
        dead = ess(energy) == 0  # every particle impossible: nothing to calibrate on
        return torch.where(dead, torch.ones_like(beta), beta)


def make_likelihood(skeleton, cameras, spec, options: Mapping[str, Mapping] | None = None) -> nn.Module:
    """A likelihood module from a name, a list of names or ``{name: weight}`` (weights of the log terms).

    Names are those of :data:`~torchpf.likelihoods.LIKELIHOODS`. ``options[name]`` holds constructor
    keywords of that term (e.g. ``{"silhouette": {"sigma": 0.2}}``). A module ``spec`` is returned as is; one
    name with weight 1 gives that cue itself, anything else a :class:`ProductLikelihood`.
    """
    if isinstance(spec, nn.Module):
        return spec
    options = dict(options or {})
    weights = (
        {spec: 1.0}
        if isinstance(spec, str)
        else dict(spec)
        if isinstance(spec, Mapping)
        else {name: 1.0 for name in spec}
    )
    terms = {}
    for name in weights:
        cls = LIKELIHOODS.get(name)
        kwargs = dict(options.get(name, {}))
        if not cls.needs_cameras:
            terms[name] = cls(skeleton, **kwargs)
        else:
            if cameras is None or len(cameras) == 0:
                raise ValueError(f"likelihood {name!r} needs cameras")
            terms[name] = cls(skeleton, cameras, **kwargs)
    if len(terms) == 1 and next(iter(weights.values())) == 1.0:
        return next(iter(terms.values()))
    return ProductLikelihood(terms, weights=weights)
