"""A learned success classifier: trained from the success labels a human's marks write, it gives the
reward (and the episode's end) of real-world RL where no simulator reports success (HIL-SERL).

* :mod:`.labels`: reads a labels folder (``SuccessLabelWriter``'s ``.npz`` files), splits its
  episodes into training and validation, draws class-balanced batches;
* :mod:`.model`: :class:`ClassifierSpec`, the architectures (:data:`CLASSIFIER_ARCHITECTURES`:
  ``mlp`` on the state vector, ``cnn`` on camera frames and optionally the state), save / load;
* :mod:`.train`: :func:`train_classifier` and its validation metrics;
* :mod:`.reward`: the ``classifier`` reward component of :data:`~infinirl.realworld.robot_env.REWARDS`;
* :mod:`.command`: ``infinirl train-classifier <labels_dir> --out <path>``.
"""

from infinirl.realworld.success_classifier.labels import (
    LabelledEpisodes,
    balanced_batch,
    load_labels,
    split_episodes,
)
from infinirl.realworld.success_classifier.model import (
    CLASSIFIER_ARCHITECTURES,
    ClassifierSpec,
    SuccessClassifier,
    load_classifier,
    save_classifier,
)
from infinirl.realworld.success_classifier.train import TrainSpec, classification_metrics, train_classifier

__all__ = ["CLASSIFIER_ARCHITECTURES", "ClassifierSpec", "LabelledEpisodes", "SuccessClassifier", "TrainSpec",
           "balanced_batch", "classification_metrics", "load_classifier", "load_labels", "save_classifier",
           "split_episodes", "train_classifier"]
