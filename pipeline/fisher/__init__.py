"""Exact diagonal Fisher information, Laplace posterior, goal Hessian and predictive entropy.

Pure PyTorch: no Hydra, Ray or MLflow here.
"""
