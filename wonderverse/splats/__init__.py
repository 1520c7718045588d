"""Gaussian splats: model, renderers (torch CPU tile rasteriser, gsplat CUDA), losses, densification,
trainer and INRIA-PLY I/O. Import submodules directly; this package imports nothing heavy at start-up."""
