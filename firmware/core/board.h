/* What the core needs from a board (LPC2148, host process or the unit tests). The core
 * calls these; each board implements them. */
#ifndef VC_BOARD_H
#define VC_BOARD_H
#include <stdint.h>

/* Queue bytes for the serial line (never blocks; a board may drop when its buffer is full).
 * Called from the tick (an interrupt on a board) and from the main loop, locked or not. */
void board_tx(const uint8_t *data, unsigned n);
/* A critical section: until board_unlock(the value returned) nothing that calls vc_tick or
 * vc_trigger_edge runs (the LPC2148 masks its interrupts; a board with one thread does
 * nothing). Sections nest. The core calls vc_rx and vc_poll's work unlocked and takes this
 * only around what the tick shares (valvectl.h), so the tick waits a few microseconds at
 * most, whatever the bytes received. */
uint32_t board_lock(void);
void board_unlock(uint32_t saved);
/* Open valve `valve` now for width_us microseconds (the board closes it); play_tick is the
 * play tick it belongs to (for logs). */
void board_valve_pulse(unsigned valve, uint16_t width_us, uint32_t play_tick);
/* Close every valve at once and cancel pending closes. */
void board_valves_off(void);
/* Bit v set while valve v is open. */
uint8_t board_outputs(void);
/* Something a log may want: VC_NOTE_ABORT / VC_NOTE_FAULT / VC_NOTE_DONE (a, b below). */
enum { VC_NOTE_ABORT = 1, VC_NOTE_FAULT = 2, VC_NOTE_DONE = 3, VC_NOTE_START = 4 };
void board_note(int what, uint32_t a, uint32_t b);
#ifdef VC_HOST_BUILD
/* STALL command: stop feeding the watchdog for ms (host builds only). */
void board_stall(uint32_t ms);
#endif

#endif
