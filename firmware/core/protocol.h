/* Valve controller link: constants of firmware/PROTOCOL.md (the one normative text).
 * Portable C99, no hardware access. Thesis 2.3.1 (LPC-H2148 valve microcontroller). */
#ifndef VC_PROTOCOL_H
#define VC_PROTOCOL_H

#include <stdint.h>

#define VC_PROTOCOL_VERSION 1u
#define VC_MARK0 0xA5u
#define VC_MARK1 0x5Au
#define VC_MAX_PAYLOAD 240u            /* LEN 0..240 */
#define VC_FRAME_OVERHEAD 7u           /* marker 2, LEN, SEQ, TYPE, CRC 2 */
#define VC_MAX_FRAME (VC_MAX_PAYLOAD + VC_FRAME_OVERHEAD)
#define VC_BYTE_TIMEOUT_MS 50u         /* a frame not completed within 50 ms: TRUNCATED */

#define VC_N_VALVES 2u                 /* 0 = part (water), 1 = scaffold */
#define VC_TICK_US 2000u               /* thesis 2.3.1: 2 ms resolution */
#define VC_STORE_BYTES 12288u          /* program ring per valve */
#define VC_QUEUE 4u                    /* programs queued per valve */
#define VC_MAX_DATA (VC_MAX_PAYLOAD - 5u)  /* PROG_DATA bytes per frame: 235 */
#define VC_MAX_PULSES 16384u           /* thesis 2.3.1: 16 384 entries per piece */
#define VC_MAX_PIECE_US 131072000u     /* thesis 2.3.1: 131.072 s per piece */
#define VC_DEFAULT_PULSE_US 500u       /* flow.calibration_pulse_ms */
#define VC_WATCHDOG_MS 10000u          /* thesis 2.3.1: 10 s watchdog */

/* commands (host -> controller); replies are TYPE | 0x80 */
enum {
    VC_HELLO = 0x01, VC_STATUS = 0x02, VC_CONFIG = 0x03,
    VC_PROG_BEGIN = 0x10, VC_PROG_DATA = 0x11, VC_PROG_VERIFY = 0x12,
    VC_ARM = 0x20, VC_ABORT = 0x21, VC_TRIGGER = 0x22,
    VC_STALL = 0x70
};
/* events and errors (controller -> host) */
enum { VC_EV_DONE = 0xE1, VC_EV_FAULT = 0xE2, VC_EV_BOOT = 0xE3, VC_ERROR = 0xFF };

enum { VC_IDLE = 0, VC_LOADED = 1, VC_ARMED = 2, VC_PLAYING = 3, VC_FAULT = 4 };

enum { VC_FAULT_NONE = 0, VC_FAULT_WATCHDOG = 1, VC_FAULT_UNDERRUN = 2,
       VC_FAULT_INTERNAL = 3, VC_FAULT_BAD_STREAM = 4 };

enum {
    VC_E_CRC = 1, VC_E_TRUNCATED = 2, VC_E_OVERSIZE = 3, VC_E_NOISE = 4,
    VC_E_SEQUENCE = 5, VC_E_UNKNOWN_TYPE = 6, VC_E_BAD_LENGTH = 7, VC_E_STATE = 8,
    VC_E_NO_ROOM = 9, VC_E_PROGRAM = 10, VC_E_OFFSET = 11, VC_E_BAD_VALUE = 12,
    VC_E_TRIGGER = 13
};

enum { VC_RESET_POWER = 0, VC_RESET_WATCHDOG = 1, VC_RESET_BROWNOUT = 2 };

#endif
