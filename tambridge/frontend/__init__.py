"""Tracking-centred frontends: ORB RGB-D SLAM (:mod:`tambridge.frontend.orb`, the default) and Open3D RGB-D
odometry (:mod:`tambridge.frontend.open3d`: keyframes with a pose graph, or frame to frame).

Each follows :class:`~tambridge.frontend.contract.Frontend`; :func:`~tambridge.frontend.factory.make_frontend`
builds the one a config names. Nothing heavy is imported here, so that importing the contract or the configs does
not load Open3D and numba.
"""
