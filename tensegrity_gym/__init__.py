"""tensegrity_gym: Gymnasium environments for a six-rod tensegrity, on MuJoCo or on an identified twin."""

__version__ = "0.1.0"
