"""Contact as energy: terms of the step's incremental potential, solved with the cloth in one Newton solve
(``[collision] method = "barrier"``). See :mod:`implicit_cloth.contact.obstacles`."""

from .obstacles import Contacts, ObstacleBarrier, ObstacleContact, ObstacleFriction

__all__ = ["Contacts", "ObstacleBarrier", "ObstacleContact", "ObstacleFriction"]
