"""identified: a first-principles, differentiable spring-rod engine identified by linear regression.

Knows spring-rod systems, tensors and data; knows nothing of Gymnasium (never imports
``tensegrity_gym``) and never steps MuJoCo.
"""

from identified.dataset import Dataset, DatasetError, load_dataset, save_dataset
from identified.topology import Topology, TopologyError

__all__ = ["Dataset", "DatasetError", "Topology", "TopologyError", "load_dataset", "save_dataset"]
__version__ = "0.1.0"
