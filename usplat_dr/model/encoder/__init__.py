"""The MVSplat-equivalent encoder: backbone, cost volume, U-Nets, depth predictor."""

from usplat_dr.model.encoder.primary import PrimaryNetwork, PrimaryNetworkCfg

__all__ = ["PrimaryNetwork", "PrimaryNetworkCfg"]
