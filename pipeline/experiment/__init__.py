"""The experiment pipeline: the only package importing Hydra, OmegaConf, Ray and MLflow."""
