/* The valve controller core: frame parser, command handling, state machine and pulse
 * scheduler (PROTOCOL.md). Portable C99, no hardware access: a board feeds it received
 * bytes (vc_rx), the time for the byte timeout (vc_poll), one call per valve tick
 * (vc_tick) and trigger edges (vc_trigger_edge), and implements board.h.
 *
 * Concurrency: vc_tick and vc_trigger_edge may interrupt vc_rx and vc_poll (on the LPC2148
 * the tick runs in the timer interrupt, vc_rx / vc_poll in the main loop with interrupts
 * on). The link fields below (fb .. cache, reply_due) are the main loop's alone (the
 * tick's TRIGGER error only reads the byte `expected`): framing, CRCs, a PROG_DATA's
 * validation, its copy into free ring space and a reply's CRC run unlocked, so an event
 * the tick sends between a command's lock and its reply's sending goes out before that
 * reply (events are unsolicited, PROTOCOL.md 3). Everything the tick reads or writes
 * (state, stores, counters, ev_seq, the board's transmit queue) is touched by the main loop only between board_lock() and
 * board_unlock() (board.h), in sections of bounded, input-independent work (~10-15 us on
 * the LPC2148): before, the board ran all of vc_rx with interrupts off, ~0.9 ms for a
 * PROG_DATA frame, 28 ms for crafted start markers (BENCHMARKS.md, "Valve firmware: work
 * with interrupts off"). The rest is not reentrant: one main loop, one tick. */
#ifndef VC_VALVECTL_H
#define VC_VALVECTL_H

#include <stdint.h>
#include "protocol.h"
#include "program.h"

typedef struct {
    /* link */
    uint8_t fb[VC_MAX_FRAME];
    uint16_t flen;
    uint16_t crc_n;          /* fb[2 .. 2 + crc_n) is in crc_run (0: nothing yet) */
    uint16_t crc_run;
    uint32_t last_rx_ms;
    uint32_t noise;
    uint8_t expected;
    uint8_t have_cache;
    uint8_t cache_len;
    uint8_t cache[VC_FRAME_OVERHEAD + 64];
    uint8_t reply_due;       /* cache holds a reply whose CRC and sending are still due */
    uint8_t ev_seq;
    uint32_t errors_sent;
    /* state */
    uint8_t state, fault, last_fault;
    uint8_t armed_mask;      /* ARMED: armed; PLAYING: playing */
    uint8_t queued_mask;     /* PLAYING: ARM queued behind */
    uint8_t done_mask;       /* PLAYING: valves whose program ended */
    uint8_t trig_latched;    /* an edge since the last tick */
    uint8_t early_trigger;   /* PLAYING with a queued arm: the next play's trigger came */
    uint32_t early_ticks;    /* ticks it has waited */
    uint32_t play_tick;      /* tick of the current play to be handled next */
    uint32_t late_ticks;
    uint32_t play_len;
    uint16_t plays;
    uint32_t last_emitted[VC_N_VALVES];
    uint8_t wait_for_data;   /* virtual clock: a tick waits for missing bytes (no UNDERRUN) */
    uint8_t resume;          /* the last tick waited: the next call finishes it */
    vc_store store[VC_N_VALVES];
} vc_core;

void vc_init(vc_core *c, uint8_t reset_cause);
void vc_rx(vc_core *c, const uint8_t *data, unsigned n, uint32_t now_ms);
void vc_poll(vc_core *c, uint32_t now_ms);
/* Returns 1 when the tick was handled, 0 when it waits for program bytes (only with
 * wait_for_data set; call again with the same tick when bytes came). */
int vc_tick(vc_core *c, int late);
void vc_trigger_edge(vc_core *c);
/* Virtual clock: 1 if the next tick can run without waiting for program bytes. */
int vc_can_advance(vc_core *c);
/* 1 while a tick has work: playing, or a trigger edge is latched. */
int vc_needs_tick(const vc_core *c);
/* Enter FAULT (every valve off, programs discarded, FAULT event). */
void vc_fault(vc_core *c, uint8_t fault);

#endif
