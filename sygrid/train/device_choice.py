"""The ``--device`` choices of the trainers (standard library only: the command lines read them without torch)."""

DEVICE_CHOICES = ("auto", "cpu", "cuda")
