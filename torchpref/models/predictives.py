r"""Predictive quantities of :class:`~torchpref.models.preference_gp.PreferenceGP` beyond BoTorch's
``posterior``: marginals, expected ratings and levels, preference and tie probabilities (eq. 11),
and the best item."""

from __future__ import annotations

import torch
from torch import Tensor

from torchpref.likelihoods.ordinal import OrdinalRatingLikelihood


class Predictives:
    """Eq. 11's predictives. Mixed into :class:`~torchpref.models.preference_gp.PreferenceGP`; relies on its
    ``_prediction_inputs``, ``_predict``, ``posterior``, ``likelihood``, ``batch_shape``,
    ``train_X`` and ``ties_offered``."""

    def marginals(self, X: Tensor) -> tuple[Tensor, Tensor]:
        r"""Posterior mean and variance of the latent utility at each row of ``X`` (``... x d``),
        each of ``X``'s shape without its last dimension: what ``posterior(X.unsqueeze(-2))``
        gives, without building a batch of ``1 x 1`` covariances and distribution objects. For a
        batched model, ``X`` is ``... x batch_shape x m x d``."""
        Xt = self._prediction_inputs(X)
        if X.shape[:-1].numel() == 0:  # an empty batch: empty results
            empty = Xt.new_zeros(X.shape[:-1])
            return empty, empty.clone()
        if not self.batch_shape:  # one problem: all rows as one block
            Xt = Xt.reshape(-1, X.shape[-1])
        mean, var = self._predict(Xt, diag=True)
        return mean.reshape(X.shape[:-1]), var.reshape(X.shape[:-1])

    def expected_rating(self, X: Tensor) -> Tensor:
        r"""Expected rating ``Phi(m / sqrt(2 sigma_B^2 + v))`` at each row of ``X`` (``... x d``);
        returns the shape of ``X`` without its last dimension."""
        mean, var = self.marginals(X)
        return self.likelihood.rating.expected_rating(mean, var)

    def expected_level(self, X: Tensor) -> Tensor:
        r"""Expected level ``1 + sum_k Phi((m - c_k) / sqrt(sigma^2 + v))`` at each row of ``X``
        (``... x d``), for a model with ``rating_levels``."""
        return self._ordinal().expected_level(*self.marginals(X))

    def level_probabilities(self, X: Tensor) -> Tensor:
        r"""Predictive probability of each level at each row of ``X`` (``... x d``): ``... x K``."""
        return self._ordinal().level_probabilities(*self.marginals(X))

    def _ordinal(self) -> OrdinalRatingLikelihood:
        if not isinstance(self.likelihood.rating, OrdinalRatingLikelihood):
            raise ValueError("levels are predicted by a model with rating_levels=K (ordinal ratings).")
        return self.likelihood.rating

    def _pair_moments(self, Xa: Tensor, Xb: Tensor) -> tuple[Tensor, Tensor]:
        """Posterior mean and variance of ``f(a) - f(b)``, row by row."""
        if Xa.shape != Xb.shape:
            raise ValueError(f"Xa and Xb must have the same shape, got {tuple(Xa.shape)} and {tuple(Xb.shape)}.")
        mvn = self.posterior(torch.stack([Xa, Xb], dim=-2)).distribution
        m, S = mvn.mean, mvn.covariance_matrix
        return m[..., 0] - m[..., 1], S[..., 0, 0] + S[..., 1, 1] - 2 * S[..., 0, 1]

    def preference_probability(self, Xa: Tensor, Xb: Tensor) -> Tensor:
        r"""``P(a preferred to b)`` row by row (``... x d`` each): ``Phi((m_a - m_b) /
        sqrt(2 sigma_R^2 + v_a + v_b - 2 c_ab))`` (with ``ties_offered``, ``m_a - m_b - tau``)."""
        lik = self.likelihood.strict if self.ties_offered else self.likelihood.comparison
        return lik.preference_probability(*self._pair_moments(Xa, Xb))

    def tie_probability(self, Xa: Tensor, Xb: Tensor) -> Tensor:
        r"""``P(no preference between a and b)`` row by row (``... x d`` each), the tie likelihood
        integrated over the posterior of ``f(a) - f(b)``."""
        return self.likelihood.tie.tie_probability(*self._pair_moments(Xa, Xb))

    def best_item(self, X: Tensor | None = None) -> tuple[int, Tensor]:
        r"""The item of highest posterior mean utility among the rows of ``X`` (``n x d``;
        default :attr:`train_X`), in ``X``'s own coordinates (an input transform is applied as in
        :meth:`posterior`).

        Returns:
            ``(row, item)``: the row of ``X`` (the first on a tie) and that ``d`` item.

        Raises:
            ValueError: a batched model, or ``X`` not ``n x d`` with ``n >= 1``.
        """
        if self.batch_shape:
            raise ValueError(f"best_item needs a single model, this one has batch shape {tuple(self.batch_shape)}.")
        X = self.train_X if X is None else X
        d = self.train_X.shape[-1]
        if not isinstance(X, Tensor) or X.dim() != 2 or X.shape[0] < 1 or X.shape[-1] != d:
            raise ValueError(f"X must be an n x {d} tensor with n >= 1, got {getattr(X, 'shape', type(X).__name__)}.")
        with torch.no_grad():
            mean, _ = self.marginals(X)
        i = int(mean.argmax())
        return i, X[i]
