"""Image-space losses and the stroke field: SSIM/L1 fit, color transfer and Lab chroma, VGG-16 relu3 features,
FAST/NNFM/Gram/content losses, the structure-tensor stroke field, its mapping onto views, the flow score."""
from .color import (apply_color_transform, chroma, color_transfer, detail_energy, gray_gradient, lab_chroma_loss,
                    lab_chroma_stats, luminance, luminance_detail, match_detail, recolor_sh, rgb_to_lab)
from .ssim import fit_loss, psnr, ssim
from .stroke_field import (field_at_cells, field_from_doubled, field_picture, field_terms, flow_alignment_score,
                           flow_alignment_score_torch, map_field_canvas, map_field_matched, matched_view_field,
                           painting_stroke_energies, render_orientation, stroke_energies, stroke_field, stroke_hinge,
                           structure_tensor)
from .style import (StyleFeatures, StyleLoss, content_loss, fast_loss, fast_projection, fast_target, gram_loss,
                    match_style_cells, nnfm_loss)
from .vgg import VGG16Features, flatten_feats, how_to_get_weights, load_vgg, resize_style

__all__ = [
    "apply_color_transform", "chroma", "color_transfer", "detail_energy", "lab_chroma_loss", "lab_chroma_stats", "luminance",
    "luminance_detail", "match_detail", "recolor_sh", "gray_gradient",
    "rgb_to_lab",
    "fit_loss", "psnr", "ssim",
    "field_at_cells", "field_from_doubled", "field_picture", "field_terms", "flow_alignment_score",
    "flow_alignment_score_torch",
    "map_field_canvas", "map_field_matched", "matched_view_field", "painting_stroke_energies", "render_orientation",
    "stroke_energies", "stroke_field", "stroke_hinge", "structure_tensor",
    "StyleFeatures", "StyleLoss", "content_loss", "fast_loss", "fast_projection", "fast_target", "gram_loss",
    "match_style_cells", "nnfm_loss",
    "VGG16Features", "flatten_feats", "how_to_get_weights", "load_vgg", "resize_style",
]
