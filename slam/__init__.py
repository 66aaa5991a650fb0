"""voxfusion SLAM core: sparse-voxel neural implicit RGB-D SLAM (Vox-Fusion++).

Pure tensor maths and state; never imports server/, ar/, fastapi or viser.
"""

__version__ = "0.1.0"
