"""What the CEDDP says about itself in ``CeddpStats``: its versions and its Zenoh security.

``python -m arpz doctor`` and any other client read it there: a fleet's versions, whether the
router enforces access control and speaks TLS, without access to the server's files.
"""

from __future__ import annotations

from dataclasses import dataclass

from arpz.core.config import CeddpConfig
from arpz.core.version import arpz_version, zenoh_version
from arpz.transport.zenoh import config_security


@dataclass(frozen=True)
class Identity:
    arpz_version: str
    zenoh_version: str
    #: the Zenoh config carries an enabled ``access_control`` section (None: unreadable)
    access_control: bool | None
    #: the Zenoh config sets up TLS (certificate or key files)
    tls: bool | None


def identity_of(config: CeddpConfig) -> Identity:
    """Read once at start (versions from package metadata, security from ``zenoh_config``)."""
    security: tuple[bool, bool] | None = (False, False)
    if config.zenoh_config:
        security = config_security(config.zenoh_config)
    return Identity(
        arpz_version=arpz_version(),
        zenoh_version=zenoh_version(),
        access_control=security[0] if security is not None else None,
        tls=security[1] if security is not None else None,
    )
