"""Which physical effect a model is missing: the candidates ranked by the one criterion and the
stepwise `--auto` search (`explain`), the residual's shape in words (`residual_shape`), and the
protocol that would tell two look-alikes apart (`design`).

Imports from `stats`, `trials` and `fitting`.
"""
