"""tensegrity_gym: Gymnasium environments for a six-rod tensegrity, on MuJoCo or on an identified twin.

Importing the package registers ``TensegrityIco-v0`` with Gymnasium
(``gym.make("tensegrity_gym:TensegrityIco-v0")`` imports it for you).
"""

__version__ = "0.1.0"

from tensegrity_gym import envs as _envs  # noqa: F401  (registers the env ids)
