"""BoxeR-2D in miniature (seed 004): an image-plane detector for the six camera images.

- `Boxer2D`, `Boxer2DConfig`: the model (`model.py`: backbone, box-attention encoder, proposal
  stage, box-attention decoder with per-layer heads; outputs every decoder layer's logits and
  boxes).
- `BoxAttention` (`box_attention.py`), `WindowHead` (`head.py`): the paper's two parts.
- `Boxer2DCriterion`, `ImageTarget`: focal / L1 / GIoU losses weighted 2 / 5 / 2 (Table 2),
  Hungarian matching.
- `train_boxer2d`, `Boxer2DTrainConfig`: resumable, deterministic training on the fly.
- `build_boxer2d`, `load_boxer2d`, `save_boxer2d`: `detectors/weights/boxer2d.pt`.
- `frame_inputs`, `frame_targets`, `decode_image`: frames in, detections out.
- `dump_coco`, `coco_ap`: COCO results (with logits and per-layer boxes) + instances on a
  split, and pycocotools AP / AP50 / AP75 per class.

See docs/detectors.md, section "boxer2d".
"""

from detectors.boxer2d.box_attention import BoxAttention
from detectors.boxer2d.coco_results import DumpFiles, coco_ap, dump_coco
from detectors.boxer2d.config import Boxer2DConfig
from detectors.boxer2d.criterion import Boxer2DCriterion, Boxer2DLossWeights, ImageTarget
from detectors.boxer2d.data import frame_inputs, frame_targets
from detectors.boxer2d.decode import decode_image
from detectors.boxer2d.head import WindowHead
from detectors.boxer2d.model import Boxer2D
from detectors.boxer2d.train import Boxer2DTrainConfig, train_boxer2d
from detectors.boxer2d.weights import WEIGHTS_FILE, build_boxer2d, load_boxer2d, save_boxer2d

__all__ = ["WEIGHTS_FILE", "BoxAttention", "Boxer2D", "Boxer2DConfig", "Boxer2DCriterion",
           "Boxer2DLossWeights", "Boxer2DTrainConfig", "DumpFiles", "ImageTarget",
           "WindowHead", "build_boxer2d", "coco_ap", "decode_image", "dump_coco",
           "frame_inputs", "frame_targets", "load_boxer2d", "save_boxer2d", "train_boxer2d"]
