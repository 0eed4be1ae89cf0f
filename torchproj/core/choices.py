"""The names and defaults the ``torchproj`` command offers, in a module that imports nothing: its
parser reads them without importing torch or the library, so ``torchproj --help`` answers at once.
Each is re-exported, with the reason for its value, by the module that uses it.
"""

SIZE_LIMIT = 10 ** 8  # camera rays per state or cells per projector above which a rig is refused (core.checks)
SOLVER_NAMES = ("lf", "eo", "pgd", "fista", "adam")  # the keys of torchproj.solve.SOLVERS
OUTSIDE = ("clip", "map")  # how a solution whose bounds leave [0, 1] is shown (solve.to_projectable)
CHAINS = ("epipolar", "components")  # solve_eo's independent problems
OBJECTIVES = {"l2": None, "ssim": 0.1, "mixed": 1.0}  #: objective -> weight of the relative squared error
PSNR_DROP_DB = 1.0  # the PSNR per target an image objective may give up (solve.objectives)
COLOUR_WEIGHTS = ("channel", "grey")  # a colour camera's weights (transport.build)
FOOTPRINTS = ("nearest", "bilinear", "area")  # the cells a camera pixel's light is modelled on
DEFAULT_FOOTPRINT = "area"  # what run, solve and position model by default (transport.build)
# The weight of the penalty on neighbouring cells' differences in least-squares solves of a model
# (TransportOperator.with_smoothness: lam = weight x the target scale squared), chosen on suite seeds
# 55, 97, 1, 8080, 56 and 4321 and checked on five others (docs/accuracy.md); 0 for the paper's LF
# and EO and for the exact light's ceiling.
DEFAULT_SMOOTHNESS = 2e-4
MAPS = ("decoded", "homography")  # camera-to-projector maps (transport.planar)
ORACLES = ("geometry", "transport")  # what an oracle run takes from the simulator (pipeline.run)
DIM_THRESHOLD = 10  # 8-bit level under which a lit pixel is too dim to be a target pixel (calib.pipeline)
BLACK_THRESHOLD = 40  # the decoder's shadow mask: white minus black (8-bit levels) of a lit pixel (OpenCV's default)
RAMP_STEPS = 32  # bars of the photometric ramp a projector shows in calibration (calib.response)
