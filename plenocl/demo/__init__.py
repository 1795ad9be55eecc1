"""The built-in examples: the paper's boundary-layer experiment on synthetic data
(:mod:`.boundary_layer`, its figures in :mod:`.figures`; resumable through
:class:`plenocl.pipeline.resume.StageRunner`) and a particle-image demo
(:mod:`.particle_images`)."""
