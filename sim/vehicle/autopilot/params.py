"""Parameters: the handful a flavour exposes, enough for MAVSDK and GCS look-ups."""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mav

from sim.vehicle.autopilot.base import AutopilotConfig, Channel, MAVMessage, MixinBase, R


class ParamsMixin(MixinBase):
    """PARAM_REQUEST_LIST / PARAM_REQUEST_READ / PARAM_SET (part of ``Autopilot``)."""

    # Set by ``Autopilot.__init__``.
    config: AutopilotConfig

    def params(self) -> dict[str, float]:
        return {}

    def _handle_param(self, msg: MAVMessage, channel: Channel) -> None:
        if msg.target_system not in (0, self.config.system_id):
            return
        table = self.params()
        names = sorted(table)
        t = msg.get_type()

        def value(name: str) -> MAVMessage:
            return mav.MAVLink_param_value_message(name.encode(), float(table[name]),
                                                   R.MAV_PARAM_TYPE_REAL32, len(names),
                                                   names.index(name))
        if t == "PARAM_REQUEST_LIST":
            for name in names:
                channel.send(value(name))
        elif t == "PARAM_REQUEST_READ":
            name = _param_name(msg.param_id)
            if msg.param_index >= 0 and msg.param_index < len(names):
                name = names[msg.param_index]
            if name in table:
                channel.send(value(name))
        elif t == "PARAM_SET":
            name = _param_name(msg.param_id)
            if name in table and math.isfinite(msg.param_value):
                self.set_param(name, float(msg.param_value))
                table = self.params()
                channel.send(value(name))

    def set_param(self, name: str, value: float) -> None:
        """Apply a parameter write (flavours map names onto their config)."""


def _param_name(raw: bytes | str) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", errors="replace")
    return raw.split("\x00", 1)[0]
