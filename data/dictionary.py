"""The flight dictionary: telemetry packets and fields, flag bits, events and commands, declared once.

Like F' ``Telemetry.fppi`` / ``Events.fppi`` / ``Commands.fppi``, these are declarations, not code:
the flight channel's flag bits (``TlmFlag``), the event ids and severities (``EventId``, ``SEVERITY``),
the command argument checks (``COMMANDS``), the CCSDS packet encoder and decoder, the XTCE document
(``magstack tm xtce``) and the tables in docs/ccsds.md are all derived from the tuples below, so they
cannot disagree. Everything here is plain frozen data in the data layer: every layer may read it.

Units are in the names and in ``unit``; an integer telemetry field carries ``value = raw * lsb``.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

# ----------------------------------------------------------------------------------------------- flags


@dataclass(frozen=True)
class FlagBit:
    """One bit of the ``flag`` column (session files, flight telemetry, packets); each has one owner."""

    name: str
    value: int            # the bit's integer value (a power of two)
    owner: str            # the one component that sets it
    disqualifies: bool    # True: the row's ``dut_*`` field must not be used (fit, refit, diagnose)
    meaning: str


FLIGHT, APPLY, IMPORT, MERGE = "flight channel", "ground apply", "ground import/alignment", "ground merge"

FLAG_BITS: tuple[FlagBit, ...] = (
    FlagBit("NO_SAMPLE", 1 << 0, FLIGHT, True, "the read failed: no field in this record"),
    FlagBit("STALE", 1 << 1, FLIGHT, True, "the sample is not new"),
    FlagBit("OVERFLOW", 1 << 2, FLIGHT, True, "an axis saturated"),
    FlagBit("IMPLAUSIBLE", 1 << 3, FLIGHT, True, "beyond the sensor's range or an impossible rate of change"),
    FlagBit("UNCALIBRATED", 1 << 4, FLIGHT, False,
            "no calibrated field published (no table, missing input, saturated applier); raw field good"),
    FlagBit("OUT_OF_VALIDITY", 1 << 5, FLIGHT, False,
            "outside the active table's validity box: not calibrated on board; raw field good"),
    FlagBit("DEGRADED", 1 << 6, FLIGHT, True, "the channel is marked degraded (its samples are not trusted)"),
    FlagBit("OVERRUN", 1 << 7, FLIGHT, False, "the chip reported samples lost before this one"),
    FlagBit("REPEATED", 1 << 8, FLIGHT, False,
            "equal to the previous sample, within what the sensor's resolution makes likely"),
    FlagBit("APPLY_MISSING_INPUT", 1 << 9, APPLY, True, "`apply`: a needed input was NaN, calibrated field NaN"),
    FlagBit("APPLY_OUT_OF_VALIDITY", 1 << 10, APPLY, True,
            "`apply`: outside the table's validity box (the calibrated value is an extrapolation)"),
    FlagBit("APPLY_SATURATED", 1 << 11, APPLY, True, "`apply`: fixed-point input clipped or output saturated"),
    FlagBit("NO_REF", 1 << 12, IMPORT, True, "no reference field at this row (a gap in the reference source)"),
    FlagBit("NO_DUT", 1 << 13, IMPORT, True, "no DUT field at this row (a gap in the DUT source)"),
    FlagBit("NO_ADCS", 1 << 14, MERGE, True, "`merge`: no ADCS position/attitude within the tolerance"),
)
FLAG = {b.name: b for b in FLAG_BITS}
#: Bits that make a row's DUT field unusable; ``flag & DISQUALIFYING == 0`` is the one usability rule.
DISQUALIFYING = sum(b.value for b in FLAG_BITS if b.disqualifies)
#: ``ApplyFlag`` (the applier's own status: 1 missing input, 2 out of validity, 4 saturated) << this.
APPLY_FLAG_SHIFT = 9


def flags_of(owner: str) -> dict[str, int]:
    """``{name: value}`` of the bits one owner sets (for an ``IntFlag``)."""
    return {b.name: b.value for b in FLAG_BITS if b.owner == owner}


def flag_legend(owner: str | None = None) -> str:
    """``"1=no_sample 2=stale ..."`` (the session files' ``flag_bits`` metadata)."""
    return " ".join(f"{b.value}={b.name.lower()}" for b in FLAG_BITS if owner is None or b.owner == owner)


#: Bits that describe a good row without disqualifying it; any other bit (also one no owner declares) does.
INFORMATIONAL = sum(b.value for b in FLAG_BITS if not b.disqualifies)


def usable(flag):
    """True where no bit but the informational ones is set (works on ints and numpy arrays); an unknown
    bit disqualifies the row."""
    return (flag & ~INFORMATIONAL) == 0


# ----------------------------------------------------------------------------------------------- events


class Severity(IntEnum):
    """F' event severities."""

    DIAGNOSTIC = 0
    ACTIVITY_LO = 1
    ACTIVITY_HI = 2
    WARNING_LO = 3
    WARNING_HI = 4
    FATAL = 5


#: PUS service 5 subtype of each severity (5,1 informative .. 5,4 high severity anomaly).
EVENT_SUBTYPE = {Severity.DIAGNOSTIC: 1, Severity.ACTIVITY_LO: 1, Severity.ACTIVITY_HI: 1,
                 Severity.WARNING_LO: 2, Severity.WARNING_HI: 3, Severity.FATAL: 4}


@dataclass(frozen=True)
class EventDef:
    name: str
    id: int
    severity: Severity
    text: str


_S = Severity
#: Ids never change meaning once released. Ranges: 0x01xx executive, 0x02xx channels, 0x03xx tables,
#: 0x04xx commands, 0x05xx refit, 0x06xx telemetry.
EVENTS: tuple[EventDef, ...] = (
    EventDef("EXEC_STARTED", 0x0100, _S.ACTIVITY_HI, "executive started"),
    EventDef("EXEC_STOPPED", 0x0101, _S.ACTIVITY_HI, "executive stopped"),
    EventDef("RATE_GROUP_OVERRUN", 0x0110, _S.WARNING_LO, "a group's execution took longer than its period"),
    EventDef("RATE_GROUP_SLIP", 0x0111, _S.WARNING_LO, "slots skipped (schedule re-anchored, no catch-up burst)"),
    EventDef("CLOCK_STEPPED_BACK", 0x0112, _S.WARNING_HI, "the tick source went backwards: schedule re-anchored"),
    EventDef("CHAN_BUS_ERROR", 0x0200, _S.WARNING_LO, "bus error reading the sensor"),
    EventDef("CHAN_TIMEOUT", 0x0201, _S.WARNING_LO, "data-ready never came"),
    EventDef("CHAN_STALE", 0x0202, _S.WARNING_LO, "no new data: chip said so, or the sample repeats the last one"),
    EventDef("CHAN_OVERFLOW", 0x0203, _S.WARNING_LO, "an axis saturated"),
    EventDef("CHAN_IMPLAUSIBLE", 0x0204, _S.WARNING_LO,
             "beyond the sensor range or a physically impossible rate of change"),
    EventDef("CHAN_SELF_TEST_FAILED", 0x0205, _S.WARNING_HI, "the sensor's self-test failed"),
    EventDef("CHAN_EXCEPTION", 0x0206, _S.WARNING_HI, "a non-magstack exception caught at the component boundary"),
    EventDef("CHAN_OTHER_ERROR", 0x0207, _S.WARNING_LO, "any other typed magstack error"),
    EventDef("CHAN_OUT_OF_VALIDITY", 0x0208, _S.DIAGNOSTIC,
             "outside the active table's validity: published uncalibrated"),
    EventDef("CHAN_REINIT", 0x0210, _S.ACTIVITY_HI, "driver re-initialised"),
    EventDef("CHAN_REINIT_FAILED", 0x0211, _S.WARNING_HI, "driver re-initialisation failed"),
    EventDef("CHAN_DEGRADED", 0x0212, _S.WARNING_HI, "re-initialisations without a good sample: channel degraded"),
    EventDef("CHAN_RECOVERED", 0x0213, _S.ACTIVITY_HI, "good sample after degradation"),
    EventDef("TABLE_LOADED", 0x0300, _S.ACTIVITY_HI, "calibration table staged"),
    EventDef("TABLE_REJECTED", 0x0301, _S.WARNING_HI, "calibration table rejected"),
    EventDef("TABLE_ACTIVATED", 0x0302, _S.ACTIVITY_HI, "calibration table active"),
    EventDef("CMD_ACCEPTED", 0x0400, _S.ACTIVITY_LO, "command accepted"),
    EventDef("CMD_REJECTED", 0x0401, _S.WARNING_LO, "command rejected"),
    EventDef("CMD_COMPLETED", 0x0402, _S.ACTIVITY_LO, "command completed"),
    EventDef("REFIT_STARTED", 0x0500, _S.ACTIVITY_HI, "on-orbit refit started"),
    EventDef("REFIT_FINISHED", 0x0501, _S.ACTIVITY_HI, "on-orbit refit finished"),
    EventDef("REFIT_FAILED", 0x0502, _S.WARNING_HI, "on-orbit refit failed or stopped"),
    EventDef("TLM_FILE_ROTATED", 0x0600, _S.DIAGNOSTIC, "telemetry file rotated"),
    EventDef("TLM_WRITE_ERROR", 0x0601, _S.WARNING_HI, "a telemetry record or packet could not be written"),
    EventDef("TLM_RECOVERED", 0x0602, _S.ACTIVITY_HI, "telemetry writing resumed after a write error"),
    EventDef("TLM_QUEUE_FULL", 0x0603, _S.WARNING_HI,
             "the write-behind queue was full: records, packets or event lines dropped (counted)"),
    EventDef("TC_REJECTED", 0x0410, _S.WARNING_LO,
             "a telecommand packet was malformed, corrupt, replayed or unauthorised: counted, not executed"),
    EventDef("TC_STATE_ERROR", 0x0411, _S.WARNING_HI,
             "the telecommand receiver's saved sequence counts could not be written or read"),
    EventDef("TC_RESYNC", 0x0412, _S.ACTIVITY_HI, "a source's expected telecommand sequence count was set"),
)

# ----------------------------------------------------------------------------------------------- commands


@dataclass(frozen=True)
class ArgDef:
    """A command argument: a UTF-8 string of 1..max_len bytes (length-prefixed in a telecommand); ``kind``
    "uint": decimal digits of an integer in 0..max_value."""

    name: str
    meaning: str
    max_len: int = 255
    unit: str = ""
    kind: str = "text"
    max_value: int | None = None


def arg_problem(a: ArgDef, value: object) -> str:
    """Why ``value`` is not a valid ``a`` ("" when it is): the one argument check of the command directory,
    the telecommand receiver and ``magstack tm command``."""
    if not isinstance(value, str) or not value:
        return f"argument {a.name!r} must be a non-empty string"
    n = len(value.encode("utf-8", "surrogatepass"))
    if n > a.max_len:
        return f"argument {a.name!r} is {n} bytes, longer than {a.max_len}"
    if a.kind == "uint":
        if not (value.isascii() and value.isdigit()) or (a.max_value is not None and int(value) > a.max_value):
            return f"argument {a.name!r} must be an integer in 0..{a.max_value}, got {value[:20]!r}"
    return ""


@dataclass(frozen=True)
class CommandDef:
    name: str
    opcode: int          # the PUS 8,1 function id
    args: tuple[ArgDef, ...]
    handler: str         # FlightApp method that executes it
    meaning: str


_CH = ArgDef("channel", "sensor name from the flight configuration", 64)
_PATH = ArgDef("path", "table file, relative to the configuration file", 255)
COMMANDS: tuple[CommandDef, ...] = (
    CommandDef("load_table", 0x01, (_CH, _PATH), "_execute", "parse, check, validate and stage a table"),
    CommandDef("validate_table", 0x02, (_CH, _PATH), "_execute", "report whether a table would be accepted"),
    CommandDef("activate_table", 0x03, (_CH,), "_execute", "swap the staged table in at the next cycle boundary"),
    CommandDef("set_rate_group", 0x04, (_CH, ArgDef("group", "rate group name", 64)), "_move",
               "move a channel to another rate group at the next boundary"),
    CommandDef("dump_counters", 0x05, (), "counters", "report health counters, group statistics, event counts"),
    CommandDef("start_refit", 0x06, (_CH, ArgDef("files", "glob of telemetry files, relative to the config", 255)),
               "_start_refit", "start the on-orbit batch refit in a background worker"),
    CommandDef("stop_refit", 0x07, (_CH,), "_execute", "cancel a running refit at its next block"),
    CommandDef("resync_tc", 0x08, (ArgDef("source_id", "PUS source id whose count is set", 5, kind="uint",
                                          max_value=65535),
                                   ArgDef("seq", "the sequence count it sends next", 5, kind="uint",
                                          max_value=(1 << 14) - 1)),
               "_execute", "set the telecommand receiver's expected sequence count of a source (resynchronise)"),
)
COMMAND = {c.name: c for c in COMMANDS}
COMMAND_BY_OPCODE = {c.opcode: c for c in COMMANDS}

# ----------------------------------------------------------------------------------------------- packets


@dataclass(frozen=True)
class CucFormat:
    """CCSDS Unsegmented time Code (CCSDS 301.0-B-4 sec. 3.2) of every TM packet's PUS timestamp.

    Implicit P-field (not transmitted): agency-defined epoch, ``coarse_octets`` of seconds and
    ``fine_octets`` of binary fraction."""

    epoch: str = "1970-01-01T00:00:00Z"    # UTC; the flight clock's epoch seconds (leap seconds not counted)
    coarse_octets: int = 4
    fine_octets: int = 2

    @property
    def size(self) -> int:
        return self.coarse_octets + self.fine_octets

    @property
    def p_field(self) -> int:
        """The P-field octet this format implies (0b0_010_cc_ff: agency epoch)."""
        return (0b010 << 4) | ((self.coarse_octets - 1) << 2) | self.fine_octets


CUC = CucFormat()


@dataclass(frozen=True)
class FieldDef:
    """One payload field: big-endian integer of ``bits`` (or a UTF-8 string with a one-octet length)."""

    name: str
    kind: str                    # "int" (two's complement), "uint", "string"
    bits: int                    # size; for a string: bits of its length prefix
    unit: str = ""
    lsb: float = 1.0             # engineering value = raw * lsb
    column: str = ""             # session-file column it decodes to ("" = none)
    absent: int | None = None    # raw value that means "no value" (decoded as NaN)
    meaning: str = ""


@dataclass(frozen=True)
class PacketDef:
    """A PUS-C TM packet (service, subtype) and its payload; ``apid`` names where its APID comes from."""

    name: str
    service: int
    subtype: int
    apid: str                  # "channel", "group" or "app"
    fields: tuple[FieldDef, ...]
    meaning: str


I32_ABSENT, I16_ABSENT = -(1 << 31), -(1 << 15)
FIELD_LSB_UT = 1e-4            # 0.1 nT per count: +-214 mT range, below every sensor's resolution
TEMP_LSB_C = 0.01

CHANNEL_FIELDS: tuple[FieldDef, ...] = (
    *(FieldDef(f"raw_{a}", "int", 32, "uT", FIELD_LSB_UT, f"dut_{a}_uT", I32_ABSENT, f"sensor output, {a} axis")
      for a in "xyz"),
    *(FieldDef(f"cal_{a}", "int", 32, "uT", FIELD_LSB_UT, f"cal_{a}_uT", I32_ABSENT, f"calibrated field, {a} axis")
      for a in "xyz"),
    FieldDef("temp", "int", 16, "degC", TEMP_LSB_C, "temp_c", I16_ABSENT, "sensor temperature"),
    FieldDef("flag", "uint", 16, "", 1.0, "flag", None, "flag bits (FLAG_BITS)"),
    FieldDef("table_crc32", "uint", 32, "", 1.0, "table_crc32", 0, "CRC-32 of the table used; 0 = none"),
    FieldDef("error_count", "uint", 32, "", 1.0, "error_count", None, "channel's total faults so far"),
    FieldDef("run_id", "uint", 32, "", 1.0, "session", None,
             "the flight run (apid_map names this APID within this run)"),
)
_STR = "string"
GROUP_HK_FIELDS: tuple[FieldDef, ...] = (
    FieldDef("runs", "uint", 32, "", meaning="cycles run"),
    FieldDef("overruns", "uint", 32, "", meaning="cycles longer than the period"),
    FieldDef("missed_slots", "uint", 32, "", meaning="slots skipped (slips)"),
    FieldDef("clock_steps_back", "uint", 32, "", meaning="tick source went backwards"),
    FieldDef("exec_max", "uint", 32, "s", 1e-6, meaning="longest cycle"),
)
APP_HK_FIELDS: tuple[FieldDef, ...] = (
    FieldDef("tc_accepted", "uint", 32, meaning="telecommands accepted"),
    FieldDef("tc_rejected", "uint", 32, meaning="telecommand packets refused (sum of the counts below)"),
    FieldDef("tc_malformed", "uint", 32, meaning="truncated, bad length or undecodable"),
    FieldDef("tc_bad_crc", "uint", 32, meaning="packet error control (CRC-16) wrong"),
    FieldDef("tc_wrong_apid", "uint", 32, meaning="not addressed to this application"),
    FieldDef("tc_replayed", "uint", 32, meaning="sequence count in the window behind the expected one (a replay)"),
    FieldDef("tc_out_of_window", "uint", 32, meaning="sequence count outside both windows (resync_tc sets it)"),
    FieldDef("tc_unauthorised", "uint", 32, meaning="source address or PUS source id not configured"),
    FieldDef("tc_invalid", "uint", 32, meaning="unknown service, function id or bad arguments"),
    FieldDef("tm_send_errors", "uint", 32, meaning="packets the stream could not write or send"),
)
ID_FIELDS: tuple[FieldDef, ...] = (
    FieldDef("apid", "uint", 16, meaning="the APID described"),
    FieldDef("kind", "uint", 8, meaning="1 channel, 2 rate group"),
    FieldDef("run_id", "uint", 32, meaning="the flight run (session column)"),
    FieldDef("name", _STR, 8, meaning="channel or rate group name"),
    FieldDef("device_id", _STR, 8, meaning="the channel's device id"),
    FieldDef("chip", _STR, 8, meaning="the channel's chip"),
)
EVENT_FIELDS: tuple[FieldDef, ...] = (
    FieldDef("event_id", "uint", 16, meaning="EVENTS id"),
    FieldDef("severity", "uint", 8, meaning="Severity"),
    FieldDef("source", _STR, 8, meaning="channel, group or command source"),
    FieldDef("message", _STR, 8, meaning="text"),
)
_REQ = (FieldDef("tc_packet_id", "uint", 16, meaning="request id: the TC's packet id"),
        FieldDef("tc_seq_ctrl", "uint", 16, meaning="request id: the TC's sequence control"))
_FAIL = (FieldDef("failure_code", "uint", 16, meaning="TC_FAILURE code"),)

TM_PACKETS: tuple[PacketDef, ...] = (
    PacketDef("channel", 3, 25, "channel", CHANNEL_FIELDS, "one magnetometer record per cycle"),
    PacketDef("group_hk", 3, 25, "group", GROUP_HK_FIELDS, "rate-group housekeeping every hk_period_s"),
    PacketDef("app_hk", 3, 25, "app", APP_HK_FIELDS, "telecommand counters every hk_period_s"),
    PacketDef("apid_map", 3, 128, "app", ID_FIELDS,
              "names each channel/group APID of a run (before the run's first packet, then every hk_period_s)"),
    PacketDef("event", 5, 0, "app", EVENT_FIELDS, "every event; subtype 1..4 from the severity"),
    PacketDef("accept_ok", 1, 1, "app", _REQ, "telecommand accepted"),
    PacketDef("accept_fail", 1, 2, "app", _REQ + _FAIL, "telecommand refused"),
    PacketDef("complete_ok", 1, 7, "app", _REQ, "command completed"),
    PacketDef("complete_fail", 1, 8, "app", _REQ + _FAIL, "command failed"),
    PacketDef("ping_reply", 17, 2, "app", (), "reply to a 17,1 ping"),
)
TM_PACKET = {p.name: p for p in TM_PACKETS}


class TcFailure(IntEnum):
    """Failure codes in 1,2 / 1,8 reports."""

    MALFORMED = 1
    BAD_CRC = 2
    WRONG_APID = 3
    REPLAYED = 4
    UNAUTHORISED = 5
    UNKNOWN_COMMAND = 6
    BAD_ARGUMENT = 7
    EXECUTION_FAILED = 8
    OUT_OF_WINDOW = 9


#: APIDs: telecommands, events, reports and app housekeeping on APP_APID; channel i on CHANNEL_APID0 + i;
#: rate group j's housekeeping on GROUP_APID0 + j (in configuration order).
APP_APID, CHANNEL_APID0, GROUP_APID0 = 0x0F0, 0x100, 0x180
MAX_CHANNELS, MAX_GROUPS = 0x80, 0x70
#: PUS-C telecommands: 17,1 ping; 8,1 perform function (function id = CommandDef.opcode).
TC_PING, TC_FUNCTION = (17, 1), (8, 1)
