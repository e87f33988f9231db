"""Push-pull language fields (PPGS) on surfels or Gaussians: features, autoencoder, bridge, losses, queries.

Importing this package registers the losses (`lang_feature`, `bridge_color`, `bridge_feature`, `ppgs`) and the
trainer extension `language`; a training config lists it under `imports: [warpgs.language]`. Warp is not
imported here (only rendering for queries loads it).

Modules, one job each:
    text          phrase -> unit embedding (offline hash stand-in; CLIP in `clip`)
    features_io   LangSplat-style .npy per view (segment map + one feature per segment)
    standin       stand-in features from label maps
    clip          optional real extraction (open_clip + segment-anything, local weights only)
    autoencoder   512 -> d -> 512 scene autoencoder
    targets       feature folder -> autoencoder -> per-view latent target maps
    bridge        positional encoding + shared trunk + colour / language heads
    losses        L_r, L_c, L_f, joint homoscedastic weighting (registered)
    settings      LanguageConfig (the extension's options)
    extension     the trainer extension
    query         relevancy maps, masks, 3D selection, delete / extract, click-to-segment
    evaluate      mIoU / mAP against label maps
    cli           `warpgs-query`
"""
from warpgs.language import losses as _losses  # noqa: F401  (registers the loss terms)
from warpgs.language.autoencoder import FeatureAutoencoder, train_autoencoder
from warpgs.language.bridge import BridgeMLP, positional_encoding
from warpgs.language.extension import LanguageFieldExtension
from warpgs.language.features_io import load_view_features, save_view_features
from warpgs.language.losses import (HomoscedasticWeights, LanguageContext, active_branch, beta_from_uncertainty,
                                    bidirectional_loss)
from warpgs.language.query import LanguageField, QueryResult
from warpgs.language.settings import LanguageConfig
from warpgs.language.standin import write_standin_features
from warpgs.language.text import CANONICAL_NEGATIVES, HashTextEncoder, hash_embedding

__all__ = [
    "FeatureAutoencoder", "train_autoencoder", "BridgeMLP", "positional_encoding", "LanguageFieldExtension",
    "load_view_features", "save_view_features", "HomoscedasticWeights", "LanguageContext", "active_branch",
    "beta_from_uncertainty", "bidirectional_loss", "LanguageField", "QueryResult", "LanguageConfig",
    "write_standin_features", "CANONICAL_NEGATIVES", "HashTextEncoder", "hash_embedding",
]
