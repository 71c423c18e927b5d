"""Datasets loaded offline and verified (MNIST for the VAE domain)."""

from asp_dist.data.mnist import MNIST, MNISTError, load_mnist

__all__ = ["MNIST", "MNISTError", "load_mnist"]
