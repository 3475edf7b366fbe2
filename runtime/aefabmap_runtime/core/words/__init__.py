"""Words: descriptors to visual word ids (k-means, vocabulary tree, autoencoder ONNX graphs)."""
