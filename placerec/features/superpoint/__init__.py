"""SuperPoint for LiDAR intensity images: the network (`arch`, `torch_model`, `onnx_graph`), its weights files
(`weights`), the NumPy post-processing (`post`) and the registered ``superpoint`` extractor (`extractor`).
Trained by ``tools/train_superpoint.py`` (`placerec.artifacts.superpoint`); see docs/superpoint.md."""
