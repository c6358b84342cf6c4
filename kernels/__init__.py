"""Warp kernels and ``wp.func`` physics of warpdem, installed as :mod:`warpdem.kernels`.

Modules hold kernels and device functions only: no allocation and no host logic. Each module has a host
counterpart of the same name in :mod:`warpdem` that launches its kernels.
"""
