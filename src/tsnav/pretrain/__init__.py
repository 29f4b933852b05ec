"""Encoder pretraining (paper §III-C, Table III): DE-MAE, standard MAE, DE-MAE w/ crop, ResNet18 baseline.

Modules:
    model       MaskedAutoencoderViT (timm-layout ViT encoder, MAE decoder, RGB and depth heads), weight loading
    resnet      ResNet18 in torchvision's layout (the baseline encoder)
    data        RGB-D frames of the train scenes, batched flip / crop, normalisation
    train       the resumable, distributed pretraining loop (``tsnav pretrain``, see ``command``)
    checkpoint  safetensors + JSON checkpoints, atomic writes
    viz         reconstruction pictures
    features    the per-scene feature cache (``tsnav features``)
    probe       linear probes (depth RMSE, visible-category mAP) to compare encoders
    synthetic   a tiny synthetic RGB-D dataset for tests and benchmarks
"""
