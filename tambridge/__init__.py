"""tambridge: RGB-D SLAM and 3D Gaussian Splatting reconstruction that runs on a CPU.

Data flows one way: ``io`` (sequence readers) -> ``frontend`` (tracking) -> ``bridge`` (view
selection and pose refinement) -> ``gaussians`` (online 3DGS mapper) -> ``export`` -> ``evaluation``.
Poses are 4x4 float64 ``world_from_camera`` matrices in the OpenCV camera frame; depth is in metres.
"""

__version__ = "0.1.0"
