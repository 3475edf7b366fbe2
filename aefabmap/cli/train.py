"""`aefabmap train`: learn a vocabulary and Chow-Liu tree from training images, write a bundle."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from aefabmap.cli.options import TRAIN_EXTRA_MODULES, require_extra
from aefabmap_runtime.core.features.feature_kinds import kind_names
from aefabmap_runtime.core.features.features import FeatureConfig


def register(sub) -> None:
    p = sub.add_parser("train", help="train a model bundle from image directories")
    io = p.add_argument_group("input and output")
    io.add_argument("--images", nargs="+", required=True, type=Path, metavar="DIR", help="training image directories (recursive)")
    io.add_argument("--out", type=Path, required=True, metavar="BUNDLE",
                    help="the bundle directory to write (manifest, vocabulary, Chow-Liu tree)")
    io.add_argument("--cache", type=Path, default=None, metavar="DIR", help="keep extracted training features here between runs")
    io.add_argument("--seed", type=int, default=0,
                    help="seed of every random choice (descriptor sample, k-means, warps, autoencoder; default 0)")
    io.add_argument("--no-progress", action="store_true", help="no progress bars on stderr")
    fe = p.add_argument_group("features (also used at run time: stored in the bundle)")
    fe.add_argument("--features", choices=kind_names(), default="orb",
                    help="keypoint detector and descriptor (default orb)")
    fe.add_argument("--rootsift", action="store_true", help="RootSIFT descriptors (with --features sift)")
    fe.add_argument("--max-features", type=int, default=500, help="keypoints per image (default 500)")
    fe.add_argument("--long-side", type=int, default=512,
                    help="resize images so the long side has this many px before detection, in training and at run "
                    "time (0: native; default 512, docs/results.md \"Detection scale\")")
    fe.add_argument("--contrast-stretch", action=argparse.BooleanOptionalAction, default=True,
                    help="stretch each image's grey levels (1st..99th percentile to 0..255) before detection, in "
                    "training and at run time (FeatureConfig.contrast_stretch; default on)")
    fe.add_argument("--clahe", action="store_true",
                    help="equalise contrast locally (CLAHE) before detection, in training and at run time (FeatureConfig)")
    fe.add_argument("--descriptor", choices=("brief", "learned"), default="brief",
                    help="ORB's descriptor: its own tests (brief, default) or a projection learned first from the "
                    "training images under homographies and synthetic night (learned, experimental: more revisits, "
                    "but some trainings publish wrong loops, so check the bundle on your own sequences; stored in "
                    "the bundle; docs/results.md \"A learned descriptor\")")
    fe.add_argument("--descriptor-images", type=int, default=2400,
                    help="--descriptor learned: training images that give keypoint pairs (default 2400)")
    fe.add_argument("--descriptor-epochs", type=int, default=6,
                    help="--descriptor learned: passes over the pairs (default 6)")
    fe.add_argument("--descriptor-warp", choices=("residual", "wide"), default="residual",
                    help="--descriptor learned: the viewpoint changes its pairs are seen under: residual (default: "
                    "only what the pyramid and the orientation leave of a viewpoint change) or wide (rotations of 20 "
                    "degrees, scales of 0.75-1.25; docs/results.md \"A learned descriptor\")")
    vo = p.add_argument_group("vocabulary (quantiser)")
    vo.add_argument("--quantizer", choices=("kmeans", "kmeans-tree", "ae"), default="kmeans",
                    help="kmeans: flat vocabulary (default); kmeans-tree: vocabulary tree, a word in "
                    "O(branching x depth) distances (ORB: bit centres, popcount); ae: autoencoder")
    vo.add_argument("--words", type=int, default=2000, help="vocabulary size K (default 2000)")
    vo.add_argument("--max-descriptors", type=int, default=200_000,
                    help="descriptors sampled for clustering (default 200000; --quantizer ae: at least --ae-descriptors)")
    vo.add_argument("--branching", type=int, default=10, help="children per node of --quantizer kmeans-tree (default 10)")
    vo.add_argument("--index-buckets", type=int, default=0, metavar="S",
                    help="--quantizer kmeans: add an inverted index of S buckets (same words as the flat search, "
                    "fewer distances; 0: none, default)")
    vo.add_argument("--vocabulary-from", type=Path, default=None, metavar="BUNDLE",
                    help="--quantizer kmeans: reuse this k-means bundle's centroids (same features and --words) "
                    "instead of clustering again")
    vo.add_argument("--float-centers", action="store_true",
                    help="kmeans-tree on a binary kind: mean (float) centres and L2 on unpacked bits instead of "
                    "bit centres and popcount (slower; for comparison)")
    ae = p.add_argument_group("autoencoder training (--quantizer ae)")
    ae.add_argument("--ae-objective", choices=("recon", "assign"), default="assign",
                    help="assign (default): train encoder and words so that views of one scene point share a word "
                    "(--ae-arch light); recon: reconstruction (+ --ae-match-weight) then k-means on the codes")
    ae.add_argument("--ae-arch", choices=("paper", "light"), default="light",
                    help="autoencoder: a light MLP (default; fast to train and run) or the paper's 1-D conv stack "
                    "(with --ae-objective recon)")
    ae.add_argument("--ae-latent", type=int, default=None, help="latent code size (default: paper D/2, light 32)")
    ae.add_argument("--ae-epochs", type=int, default=8, help="autoencoder epochs (default 8)")
    ae.add_argument("--ae-descriptors", type=int, default=250_000,
                    help="descriptors the autoencoder trains on (default 250000)")
    ae.add_argument("--ae-learning-rate", type=float, default=2e-3, help="autoencoder Adam learning rate (default 0.002)")
    ae.add_argument("--ae-patience", type=int, default=2,
                    help="epochs without held-out improvement before stopping (default 2)")
    ae.add_argument("--ae-budget-s", type=float, default=None, metavar="S",
                    help="wall-clock budget for autoencoder training (s; default: none)")
    ae.add_argument("--ae-threads", type=int, default=1,
                    help="threads of the autoencoder stages (training, ONNX; default 1)")
    ae.add_argument("--ae-warp-images", type=int, default=0,
                    help="training images warped by random homographies to give matching pairs (default 0)")
    ae.add_argument("--ae-frame-pairs", type=int, default=0,
                    help="consecutive-frame pairs of the training drives matched to give matching pairs (default 0)")
    rc = p.add_argument_group("autoencoder matching term (--ae-objective recon)")
    rc.add_argument("--ae-match-weight", type=float, default=0.0,
                    help="weight of the matching term on latent codes (0: reconstruction only, default)")
    rc.add_argument("--ae-match-negatives", choices=("batch", "image"), default="batch",
                    help="negatives of the matching term: any training pair (default), or pairs of the same image")
    asg = p.add_argument_group("autoencoder word assignment (--ae-objective assign)")
    asg.add_argument("--ae-views", type=int, default=6,
                     help="views per scene point (image + warped, darkened copies; default 6)")
    asg.add_argument("--ae-light-views", type=int, default=0,
                     help="how many of the copies are the unwarped image at a random night (pairs that differ in "
                     "light alone; default 0)")
    asg.add_argument("--ae-track-images", type=int, default=1500,
                     help="training images that give multi-view tracks (default 1500)")
    asg.add_argument("--ae-balance-weight", type=float, default=1.0, help="weight of the word-usage term (default 1)")
    asg.add_argument("--ae-recon-weight", type=float, default=1.0,
                     help="weight of the reconstruction term (default 1)")
    asg.add_argument("--ae-temperature-end", type=float, default=0.3,
                     help="temperature of the soft word assignment after annealing, in codebook spacings "
                     "(default 0.3)")
    asg.add_argument("--ae-init", choices=("random", "kmeans"), default="random",
                     help="start from a random encoder, or from the principal axes of the descriptors and k-means "
                     "words on them (default random)")
    p.set_defaults(func=run)


def run(args) -> int:
    require_extra("train", "train", TRAIN_EXTRA_MODULES)
    from aefabmap_trainer.learned_descriptor import DescriptorTraining
    from aefabmap_trainer.train import TrainConfig, train_bundle

    features = FeatureConfig(
        kind=args.features,
        max_features=args.max_features,
        long_side=args.long_side or None,
        rootsift=args.rootsift,
        clahe=args.clahe,
        contrast_stretch=args.contrast_stretch,
        descriptor=args.descriptor,
    )
    config = TrainConfig(
        images=tuple(args.images),
        out=args.out,
        features=features,
        quantizer=args.quantizer,
        words=args.words,
        branching=args.branching,
        float_centers=args.float_centers,
        index_buckets=args.index_buckets,
        vocabulary_from=args.vocabulary_from,
        seed=args.seed,
        max_descriptors=args.max_descriptors,
        cache_dir=args.cache,
        descriptor_training=DescriptorTraining(images=args.descriptor_images, epochs=args.descriptor_epochs,
                                               seed=args.seed, warp=args.descriptor_warp),
        ae_epochs=args.ae_epochs,
        ae_descriptors=args.ae_descriptors,
        ae_arch=args.ae_arch,
        ae_latent=args.ae_latent,
        ae_patience=args.ae_patience,
        ae_budget_s=args.ae_budget_s,
        ae_learning_rate=args.ae_learning_rate,
        ae_match_weight=args.ae_match_weight,
        ae_warp_images=args.ae_warp_images,
        ae_frame_pairs=args.ae_frame_pairs,
        ae_threads=args.ae_threads,
        ae_match_negatives=args.ae_match_negatives,
        ae_objective=args.ae_objective,
        ae_views=args.ae_views,
        ae_track_images=args.ae_track_images,
        ae_light_views=args.ae_light_views,
        ae_balance_weight=args.ae_balance_weight,
        ae_recon_weight=args.ae_recon_weight,
        ae_temperature_end=args.ae_temperature_end,
        ae_init=args.ae_init,
        show_progress=not args.no_progress,
    )
    result = train_bundle(config)
    print(json.dumps({"bundle": str(result.path), "timings_s": result.timings_s, **result.summary}, indent=2))
    return 0
