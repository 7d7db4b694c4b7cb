"""The NOTICE log level: normal events a user must see by default, which are no warning.

``cosim`` logs at NOTICE and above unless ``-v`` asks for more: waiting for external workers or closed-loop
clients (with how to connect them) is NOTICE, not WARNING.
"""

from __future__ import annotations

import logging

NOTICE = 25  # between INFO (20) and WARNING (30)
logging.addLevelName(NOTICE, "NOTICE")
