"""The supervisor: mode machine, the mode's commands and the relay join limit over every part."""

from packpilot.config.supervisor import SupervisorConfig
from packpilot.control.supervisor.controller import Mode, Supervisor

__all__ = ["Mode", "Supervisor", "SupervisorConfig"]
