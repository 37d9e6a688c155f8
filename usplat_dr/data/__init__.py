"""Data: the field's chunk format, view samplers, shims, and synthetic scenes (``synth``)."""

from usplat_dr.data.chunks import (
                                   BadChunkError,
                                   BadSceneError,
                                   ChunkWriter,
                                   cameras_to_matrices,
                                   decode_image,
                                   encode_image,
                                   matrices_to_cameras,
                                   read_chunk,
                                   read_index,
                                   write_chunk,
                                   write_index,
)
from usplat_dr.data.dataset import DATASET_PRESETS, ChunkDataset, DatasetCfg, Summary, dataset_cfg
from usplat_dr.data.view_sampler import (
                                   StepTracker,
                                   ViewSamplerAllCfg,
                                   ViewSamplerBoundedCfg,
                                   ViewSamplerEvaluationCfg,
                                   ViewSamplingError,
                                   get_view_sampler,
                                   read_evaluation_index,
)

__all__ = [
    "DATASET_PRESETS", "BadChunkError", "BadSceneError", "ChunkDataset", "ChunkWriter",
    "DatasetCfg",
    "StepTracker", "Summary", "ViewSamplerAllCfg", "ViewSamplerBoundedCfg",
    "ViewSamplerEvaluationCfg", "ViewSamplingError", "cameras_to_matrices", "dataset_cfg",
    "decode_image", "encode_image", "get_view_sampler", "matrices_to_cameras", "read_chunk",
    "read_evaluation_index", "read_index", "write_chunk", "write_index",
]
