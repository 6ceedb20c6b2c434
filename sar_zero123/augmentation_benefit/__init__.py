"""Do generated views help a classifier that has few real views? The sparse-azimuth protocol.

Sparse-azimuth benchmark on a dataset with 17 and 15 deg chips (real MSTAR): keep K chips per class, evenly
spaced in azimuth, at 17 deg, and train the same small classifier (``SARClassifier``, a four-stage ResNet on
64 px centre crops, random +-4 px shifts) in three arms, each tested on every 15 deg chip:

- ``real_k{K}``: the K kept chips per class only (the floor);
- ``generated_k{K}``: the kept chips plus ``views_per_chip`` generated views of each, at the azimuths
  between the kept ones, from a generator that saw only the kept chips (the pipeline ``pipeline`` fine-tuned
  on them with :func:`sar_zero123.stages.run_finetune`, the views written by
  :func:`sar_zero123.augment_dataset.augment_dataset`);
- ``all_chips``: every 17 deg chip (the ceiling).

Optional arms: ``--sectors`` keeps only the chips in a ``sector_deg`` azimuth sector per class (views at
the other sectors); ``--unseen_class T72`` adds, per K, a generator fine-tuned without that class, whose views
of it are what a user gets for a new vehicle. For each generated arm, ``view_quality`` says what limits the
views: the ceiling classifier's accuracy on the generated views against their source's class, on the VAE
round trip of real 15 deg chips (the generator's decoder bound) and on the same real chips.

Variant arms, from the same fine-tuned generator per K: ``--heading_guidance H`` adds
``generated_k{K}_heading{H}`` (the plain views sampled with heading guidance ``H``, ``SARZero123Pipeline``'s
pull away from the request turned by 180 deg); ``--strength S`` adds ``generated_k{K}_strength{S}`` (the
views started from the kept chip's own latent, SDEdit); ``--same_azimuth_control`` adds the controls
``generated_k{K}_d_az0`` (and ``..._strength{S}_d_az0``): the same views made at the chip's own azimuth,
what the requested pose adds. Every plain generated arm (per K, the sector's, the unseen class's) gets the
selected variants.

``--eoc1_data`` adds the depression transfer of MSTAR's EOC-1 (:class:`DepressionTransfer`): train on the
17 deg chips of the objects whose chips that folder holds (2S1 b01, BRDM2 E-71, T72 A64, ZSU234 d08 in
``../shared/data/mstar_eoc1``), test on that folder's chips (30 deg). Arms, each with every 17 deg chip of
those serials and with ``eoc1_ks`` chips per class: ``eoc1_real_*`` (real 17 deg chips only),
``eoc1_generated_*`` (+ one view per chip at ``d_el`` = test depression - 17 deg, from a generator fine-tuned
on those 17 deg chips only, never on a test chip) and ``eoc1_generated_*_d_el0`` (+ the same number of views
at ``d_el = 0``: the control), and ``eoc1_ceiling_cv`` (a classifier trained on the test chips themselves,
cross-validated: seed i holds out fold i). ``--depression_guidance G`` adds
``eoc1_generated_*_depression{G}`` (the d_el views sampled with depression guidance G; their control is
the plain ``_d_el0``). ``--strength S`` adds ``eoc1_generated_*_strength{S}`` (the views
started from the chip's noised latent) and ``--eoc1_views_per_chip N`` (N > 1) ``eoc1_generated_*_views{N}``
(N views per chip at ``d_az = 0`` and offsets spread evenly in the gap to its neighbours), each with its
``_d_el0`` control; ``--no-eoc1_all`` drops the arms with every chip. A generator fine-tuned on one
depression has never paired two, so these arms need ``--rehearsal_data`` (a prior corpus mixed into every
generator's fine-tune, ``FinetuneConfig.rehearsal_data``). Their ``view_quality`` scores the views with
the ceiling's seed-0 classifier (trained on test-depression chips), beside the views' 17 deg sources (the
floor) and its held-out fold (the ceiling): views that moved towards the test depression score above their
sources.

Every arm trains its classifiers with the same seeds, so arms are compared seed by seed: each generated arm
carries ``gain_over_real`` (against the real-only arm with the same kept chips) and each arm whose control
ran ``gain_over_same_azimuth`` (:func:`add_paired_gains`).

Every arm writes into its own folder under ``--out`` and ends with ``result.json``; an arm whose
``result.json`` exists is skipped, a generator or an augmentation cut short resumes (run-folder rule), so
a killed run is continued by the same command. ``--out``/``results.json`` gathers every finished arm
of the folder, this invocation's first, then those of earlier invocations.

    python -m sar_zero123.augmentation_benefit --data ../shared/data/mstar --out runs/aug26 [--quick]
    python -m sar_zero123.augmentation_benefit --data ../shared/data/mstar --out runs/eoc1 --ks --no-sectors \
        --unseen_class none --eoc1_data ../shared/data/mstar_eoc1 --rehearsal_data runs/prior/corpus

Modules: :mod:`.config` (the settings, the record a resumed folder is held to), :mod:`.arms` (the arms,
EOC-1's too), :mod:`.generators` (fine-tune and views per generator), :mod:`.gains`
(paired gains, the table); the classifier's training is
:mod:`sar_zero123.training.few_view_classifier`, the chip selections :mod:`sar_zero123.data.selection`.
"""

from __future__ import annotations

from .arms import AugmentationBenefit, DepressionTransfer
from .config import AugmentationBenefitConfig, check_settings
from .gains import add_paired_gains, format_table, paired_gain, real_baseline

__all__ = [
    "AugmentationBenefit",
    "AugmentationBenefitConfig",
    "DepressionTransfer",
    "add_paired_gains",
    "check_settings",
    "format_table",
    "paired_gain",
    "real_baseline",
]
