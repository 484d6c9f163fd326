/* The valve controller core (valvectl.h, PROTOCOL.md). Thesis 2.3.1: wait for "data
 * ready", take the path's pulse list, check it with the host, wait for the C40's trigger,
 * then pulse the valves on the 2 ms tick for the whole path. */
#include <string.h>
#include "valvectl.h"
#include "crc16.h"
#include "board.h"

static void put16(uint8_t *p, uint16_t v) { p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); }
static void put32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); p[2] = (uint8_t)(v >> 16);
    p[3] = (uint8_t)(v >> 24);
}
static uint16_t get16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }
static uint32_t get32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) |
           ((uint32_t)p[3] << 24);
}

/* ------------------------------------------------------------------ sending */

/* A frame without its CRC (frame_seal adds it). */
static unsigned frame_head(uint8_t *out, uint8_t seq, uint8_t type, const uint8_t *pl,
                           unsigned len)
{
    out[0] = VC_MARK0;
    out[1] = VC_MARK1;
    out[2] = (uint8_t)len;
    out[3] = seq;
    out[4] = type;
    if (len && pl != out + 5) memcpy(out + 5, pl, len);
    return len + VC_FRAME_OVERHEAD;
}

static void frame_seal(uint8_t *out, unsigned n)
{
    put16(out + n - 2u, vc_crc16_update(VC_CRC_INIT, out + 2, n - 4u));
}

static void send(vc_core *c, uint8_t seq, uint8_t type, const uint8_t *pl, unsigned len)
{
    uint8_t f[VC_FRAME_OVERHEAD + 64];
    unsigned n = frame_head(f, seq, type, pl, len);
    (void)c;
    frame_seal(f, n);
    board_tx(f, n);
}

/* The answer to the command being handled, kept for a repeat. Commands run locked: this
 * only copies it; send_reply sums its CRC and sends it once the lock is left. */
static void reply(vc_core *c, uint8_t seq, uint8_t type, const uint8_t *pl, unsigned len)
{
    c->cache_len = (uint8_t)frame_head(c->cache, seq, type, pl, len);
    c->have_cache = 0;
    c->reply_due = 1;
}

static void send_reply(vc_core *c)
{
    if (!c->reply_due) return;
    c->reply_due = 0;
    frame_seal(c->cache, c->cache_len);
    c->have_cache = 1;
    board_tx(c->cache, c->cache_len);
}

static uint8_t shown_fault(const vc_core *c) { return c->fault ? c->fault : c->last_fault; }

static void error(vc_core *c, uint8_t code, uint8_t seq, uint8_t type, uint32_t detail,
                  int is_reply)
{
    uint8_t p[10];
    uint32_t lk = board_lock();               /* the parser's errors come unlocked */
    p[0] = code; p[1] = seq; p[2] = c->expected; p[3] = type;
    p[4] = c->state; p[5] = shown_fault(c);
    put32(p + 6, detail);
    c->errors_sent++;
    if (is_reply) reply(c, seq, VC_ERROR, p, sizeof p);
    board_unlock(lk);
    if (!is_reply) send(c, seq, VC_ERROR, p, sizeof p);
}

static void event(vc_core *c, uint8_t type, const uint8_t *pl, unsigned len)
{
    send(c, c->ev_seq++, type, pl, len);
}

/* ------------------------------------------------------------------ state */

static void clear_programs(vc_core *c)
{
    unsigned v;
    for (v = 0; v < VC_N_VALVES; v++) vc_store_clear(&c->store[v]);
    c->armed_mask = c->queued_mask = c->done_mask = 0;
    c->trig_latched = c->early_trigger = c->resume = 0;
    c->early_ticks = 0;
}

static uint8_t rest_state(vc_core *c)
{
    unsigned v;
    for (v = 0; v < VC_N_VALVES; v++)
        if (c->store[v].count) return VC_LOADED;
    return VC_IDLE;
}

void vc_fault(vc_core *c, uint8_t fault)
{
    uint8_t p[6];
    board_valves_off();                       /* first: every valve closed */
    p[0] = fault; p[1] = c->state;
    put32(p + 2, c->play_tick);
    if (c->state == VC_PLAYING) {
        unsigned v;
        for (v = 0; v < VC_N_VALVES; v++)
            c->last_emitted[v] = (c->armed_mask >> v) & 1u ? c->store[v].rd.emitted : 0u;
    }
    clear_programs(c);
    c->state = VC_FAULT;
    c->fault = c->last_fault = fault;
    event(c, VC_EV_FAULT, p, sizeof p);
    board_note(VC_NOTE_FAULT, fault, c->play_tick);
}

void vc_init(vc_core *c, uint8_t reset_cause)
{
    uint8_t p[2];
    unsigned v;
    memset(c, 0, sizeof *c);
    for (v = 0; v < VC_N_VALVES; v++) vc_store_init(&c->store[v]);
    board_valves_off();
    c->state = VC_IDLE;
    if (reset_cause == VC_RESET_WATCHDOG) {   /* thesis 2.3.1: the watchdog rebooted us */
        c->state = VC_FAULT;
        c->fault = c->last_fault = VC_FAULT_WATCHDOG;
    }
    p[0] = reset_cause; p[1] = VC_PROTOCOL_VERSION;
    event(c, VC_EV_BOOT, p, sizeof p);
}

/* The k-th queued program of valve v that the next ARM would take (0 if none). */
static vc_prog *next_to_arm(vc_core *c, unsigned v)
{
    unsigned skip = (c->state == VC_PLAYING && ((c->armed_mask >> v) & 1u)) ? 1u : 0u;
    return vc_store_at(&c->store[v], skip);
}

/* Ready to arm: complete, or the receiving tail filling the store (the rest streams). */
static int ready(vc_core *c, unsigned v, vc_prog *p)
{
    if (!p) return 0;
    if (p->complete) return 1;
    return p == vc_store_tail(&c->store[v]) && p->received >= 16u &&
           vc_store_free(&c->store[v]) < VC_MAX_DATA;
}

static uint32_t play_length(vc_core *c, uint8_t mask, int next)
{
    uint32_t len = 0, e;
    unsigned v;
    for (v = 0; v < VC_N_VALVES; v++) {
        vc_prog *p;
        if (!((mask >> v) & 1u)) continue;
        p = next ? next_to_arm(c, v) : vc_store_at(&c->store[v], 0);
        if (!p || !p->complete) return 0xFFFFFFFFu;        /* streaming: not known yet */
        e = p->ticks;
        if (e > len) len = e;
    }
    return len;
}

static int play_step(vc_core *c);

static void start_play(vc_core *c, uint32_t late0)
{
    unsigned v;
    for (v = 0; v < VC_N_VALVES; v++)
        if ((c->armed_mask >> v) & 1u) vc_reader_start(&c->store[v]);
    c->play_len = play_length(c, c->armed_mask, 0);
    c->done_mask = 0;
    c->play_tick = 0;
    c->late_ticks = late0;
    c->plays++;
    c->state = VC_PLAYING;
    board_note(VC_NOTE_START, c->plays, c->armed_mask);
}

static void finish_play(vc_core *c, uint32_t end)
{
    uint8_t p[20];
    unsigned v;
    for (v = 0; v < VC_N_VALVES; v++) {
        vc_store *s = &c->store[v];
        c->last_emitted[v] = 0;
        if (!((c->armed_mask >> v) & 1u)) continue;
        c->last_emitted[v] = s->rd.emitted;
        if (s->rd.consumed != s->progs[s->head].received) {   /* all bytes must be read */
            vc_fault(c, VC_FAULT_INTERNAL);
            return;
        }
        vc_store_pop(s);
    }
    c->play_len = end;
    if (c->queued_mask) {
        c->armed_mask = c->queued_mask;
        c->queued_mask = 0;
        c->state = VC_ARMED;
    } else {
        c->armed_mask = 0;
        c->state = rest_state(c);
    }
    put16(p, c->plays);
    put32(p + 2, end);
    put32(p + 6, c->late_ticks);
    put32(p + 10, c->last_emitted[0]);
    put32(p + 14, c->last_emitted[1]);
    p[18] = c->state;
    p[19] = 0;
    event(c, VC_EV_DONE, p, sizeof p);
    board_note(VC_NOTE_DONE, c->plays, end);
    if (c->state == VC_ARMED && c->early_trigger) {  /* next path's trigger already came */
        uint32_t waited = c->early_ticks;
        c->early_trigger = 0;
        c->early_ticks = 0;
        start_play(c, waited);
        if (!play_step(c)) c->resume = 1;              /* its tick 0 is this tick */
    }
}

/* Handle play tick c->play_tick: emit what is due, end the play when every program is.
 * Returns 0 if it waits for bytes (wait_for_data), else 1. */
static int play_step(vc_core *c)
{
    uint32_t t = c->play_tick, end = 0;
    unsigned v;
    for (v = 0; v < VC_N_VALVES; v++) {
        vc_store *s = &c->store[v];
        if (!((c->armed_mask >> v) & 1u) || ((c->done_mask >> v) & 1u)) continue;
        for (;;) {
            int rc = vc_reader_step(s);
            if (rc == VC_STEP_NEED) {                 /* the next pulse's bytes are missing */
                if (s->rd.due_tick > t) break;        /* not due yet: they may still come */
                if (c->wait_for_data) return 0;
                vc_fault(c, VC_FAULT_UNDERRUN);
                return 1;
            }
            if (rc == VC_STEP_END) { c->done_mask |= (uint8_t)(1u << v); break; }
            if (s->rd.next_tick > t) break;
            board_valve_pulse(v, s->rd.mode == 1 ? s->rd.next_width : s->pulse_us, t);
            s->rd.emitted++;
            s->rd.have_next = 0;
        }
    }
    if (c->done_mask == c->armed_mask) {
        for (v = 0; v < VC_N_VALVES; v++)
            if (((c->armed_mask >> v) & 1u) && c->store[v].rd.end_tick > end)
                end = c->store[v].rd.end_tick;
        if (t >= end) { finish_play(c, end); return 1; }
    }
    c->play_tick = t + 1u;
    return 1;
}

void vc_trigger_edge(vc_core *c) { c->trig_latched = 1; }

int vc_needs_tick(const vc_core *c)
{
    return c->state == VC_PLAYING || c->trig_latched || c->resume;
}

int vc_can_advance(vc_core *c)
{
    unsigned v;
    if (c->state != VC_PLAYING) return 1;
    for (v = 0; v < VC_N_VALVES; v++) {
        if (!((c->armed_mask >> v) & 1u) || ((c->done_mask >> v) & 1u)) continue;
        if (vc_reader_step(&c->store[v]) == VC_STEP_NEED &&
            c->store[v].rd.due_tick <= c->play_tick) return 0;
    }
    return 1;
}

int vc_tick(vc_core *c, int late)
{
    uint16_t plays;
    if (c->resume) {                          /* finish the tick that waited for bytes */
        c->resume = 0;
        if (c->state == VC_PLAYING && !play_step(c)) { c->resume = 1; return 0; }
        return 1;
    }
    /* an early trigger waits from the tick after the one that took its edge: had the
     * play been armed, that tick would have been its tick 0 (no delay) */
    if (c->early_trigger) c->early_ticks++;
    if (c->trig_latched) {                    /* sampled at the tick (PROTOCOL.md 7) */
        c->trig_latched = 0;
        if (c->state == VC_ARMED) {
            start_play(c, 0);
        } else if (c->state == VC_PLAYING && c->queued_mask && !c->early_trigger) {
            c->early_trigger = 1;
            c->early_ticks = 0;
        } else {
            error(c, VC_E_TRIGGER, 0xFF, 0xFF, c->state, 0);
        }
    }
    if (c->state != VC_PLAYING) return 1;
    if (late) c->late_ticks++;
    plays = c->plays;
    if (!play_step(c)) { c->resume = 1; return 0; }
    if (late && c->plays != plays) c->late_ticks++;   /* the next play's tick 0: this one */
    return 1;
}

/* ------------------------------------------------------------------ commands */

static void cmd_hello(vc_core *c, uint8_t seq, const uint8_t *pl, unsigned len)
{
    uint8_t p[20];
    if (len != 4) { error(c, VC_E_BAD_LENGTH, seq, VC_HELLO, len, 1); return; }
    if (pl[0] != 'R' || pl[1] != 'D' || pl[2] != 'Y' || pl[3] != VC_PROTOCOL_VERSION) {
        error(c, VC_E_BAD_VALUE, seq, VC_HELLO, 0, 1);
        return;
    }
    p[0] = VC_PROTOCOL_VERSION;
    p[1] = VC_N_VALVES;
    put16(p + 2, VC_MAX_PAYLOAD);
    put32(p + 4, VC_TICK_US);
    put32(p + 8, VC_STORE_BYTES);
    p[12] = VC_QUEUE;
    p[13] = c->state;
    p[14] = shown_fault(c);
#ifdef VC_HOST_BUILD
    p[15] = 1;
#else
    p[15] = 0;
#endif
    put16(p + 16, c->store[0].pulse_us);
    put16(p + 18, c->store[1].pulse_us);
    reply(c, seq, VC_HELLO | 0x80, p, sizeof p);
}

/* Written straight into the reply's place (copying it there was half the work with the
 * tick locked out). */
static void cmd_status(vc_core *c, uint8_t seq, unsigned len)
{
    uint8_t *p = c->cache + 5;
    unsigned v;
    if (len != 0) { error(c, VC_E_BAD_LENGTH, seq, VC_STATUS, len, 1); return; }
    p[0] = c->state;
    p[1] = shown_fault(c);
    p[2] = board_outputs();
    p[3] = c->armed_mask;
    p[4] = (uint8_t)((c->queued_mask ? 1u : 0u) | (c->early_trigger ? 2u : 0u));
    p[5] = c->expected;
    put16(p + 6, c->plays);
    put32(p + 8, c->play_tick);
    put32(p + 12, c->late_ticks);
    put32(p + 16, c->play_len);
    put32(p + 20, c->errors_sent);
    for (v = 0; v < VC_N_VALVES; v++) {
        vc_store *s = &c->store[v];
        vc_prog *t = vc_store_tail(s);
        uint8_t *q = p + 24 + 16 * v;
        q[0] = s->count;
        q[1] = (uint8_t)(t && !t->complete);
        put16(q + 2, s->pulse_us);
        put32(q + 4, vc_store_free(s));
        put32(q + 8, t ? t->received : 0u);
        put32(q + 12, (c->state == VC_PLAYING && ((c->armed_mask >> v) & 1u)) ?
              s->rd.emitted : c->last_emitted[v]);
    }
    reply(c, seq, VC_STATUS | 0x80, p, 24u + 16u * VC_N_VALVES);
}

static void cmd_config(vc_core *c, uint8_t seq, const uint8_t *pl, unsigned len)
{
    uint16_t w;
    if (len != 3) { error(c, VC_E_BAD_LENGTH, seq, VC_CONFIG, len, 1); return; }
    w = get16(pl + 1);
    if (pl[0] >= VC_N_VALVES || w == 0) { error(c, VC_E_BAD_VALUE, seq, VC_CONFIG, 0, 1); return; }
    if (c->state == VC_PLAYING || c->state == VC_ARMED || c->state == VC_FAULT) {
        error(c, VC_E_STATE, seq, VC_CONFIG, 0, 1);
        return;
    }
    c->store[pl[0]].pulse_us = w;
    reply(c, seq, VC_CONFIG | 0x80, pl, 3);
}

static void cmd_begin(vc_core *c, uint8_t seq, const uint8_t *pl, unsigned len)
{
    uint8_t p[7], v, flags;
    uint32_t total;
    vc_store *s;
    vc_prog *t;
    if (len != 6) { error(c, VC_E_BAD_LENGTH, seq, VC_PROG_BEGIN, len, 1); return; }
    v = pl[0]; flags = pl[1]; total = get32(pl + 2);
    if (v >= VC_N_VALVES || total < 16u) { error(c, VC_E_BAD_VALUE, seq, VC_PROG_BEGIN, 0, 1); return; }
    if (c->state == VC_FAULT) { error(c, VC_E_STATE, seq, VC_PROG_BEGIN, 0, 1); return; }
    s = &c->store[v];
    t = vc_store_tail(s);
    if (flags & 1u) {
        if (!t || t->locked) { error(c, VC_E_STATE, seq, VC_PROG_BEGIN, 0, 1); return; }
        vc_store_drop_tail(s);
    } else if (t && !t->complete) {
        error(c, VC_E_STATE, seq, VC_PROG_BEGIN, 0, 1);
        return;
    }
    if (vc_store_begin(s, total)) {
        if (c->state == VC_LOADED) c->state = rest_state(c);
        error(c, VC_E_NO_ROOM, seq, VC_PROG_BEGIN, vc_store_free(s), 1);
        return;
    }
    if (c->state == VC_IDLE) c->state = VC_LOADED;
    p[0] = v;
    p[1] = (uint8_t)(s->count - 1u);
    put32(p + 2, vc_store_free(s));
    p[6] = c->state;
    reply(c, seq, VC_PROG_BEGIN | 0x80, p, sizeof p);
}

/* Checks first (locked), then the bytes are validated, summed and copied into free ring
 * space unlocked: the tick reads no byte past the tail's received count and no decoder,
 * and nothing but the main loop appends. Locked again, they become the program's, unless
 * the tick faulted meanwhile (programs gone: a STATE error, as if the frame came after).
 * All of it locked held interrupts off ~0.9 ms on the board per 235 bytes. */
static void cmd_data(vc_core *c, uint32_t *lk, uint8_t seq, const uint8_t *pl, unsigned len)
{
    uint8_t p[9], v;
    uint32_t off, n, bad = 0, w, ticks = 0;
    uint16_t crc;
    vc_store *s;
    vc_prog *t;
    vc_dec d;
    int rc;
    if (len < 6) { error(c, VC_E_BAD_LENGTH, seq, VC_PROG_DATA, len, 1); return; }
    v = pl[0]; off = get32(pl + 1); n = len - 5u;
    if (v >= VC_N_VALVES) { error(c, VC_E_BAD_VALUE, seq, VC_PROG_DATA, 0, 1); return; }
    s = &c->store[v];
    t = vc_store_tail(s);
    if (c->state == VC_FAULT || !t || t->complete) {
        error(c, VC_E_STATE, seq, VC_PROG_DATA, 0, 1);
        return;
    }
    if (off != t->received) { error(c, VC_E_OFFSET, seq, VC_PROG_DATA, t->received, 1); return; }
    if (n > vc_store_free(s)) { error(c, VC_E_NO_ROOM, seq, VC_PROG_DATA, vc_store_free(s), 1); return; }
    d = t->dec;
    crc = t->crc;
    w = s->w;
    board_unlock(*lk);
    rc = vc_store_check(t, pl + 5, n, &d, &bad);
    if (!rc) {
        vc_store_put(s, w, pl + 5, n);
        crc = vc_crc16_update(crc, pl + 5, n);
        if (d.phase == VC_DEC_DONE) ticks = vc_ticks_round(d.total_us);
    }
    *lk = board_lock();
    if (c->state == VC_FAULT || vc_store_tail(s) != t) {
        error(c, VC_E_STATE, seq, VC_PROG_DATA, 0, 1);
        return;
    }
    if (!rc) {
        vc_store_commit(s, &d, crc, n);
        t->ticks = ticks;
    } else {
        if (t->locked) {
            vc_fault(c, VC_FAULT_BAD_STREAM);        /* an armed or playing program is bad */
        } else {
            vc_store_drop_tail(s);
            if (c->state == VC_LOADED) c->state = rest_state(c);
        }
        if (rc == -2) error(c, VC_E_NO_ROOM, seq, VC_PROG_DATA, vc_store_free(s), 1);
        else error(c, VC_E_PROGRAM, seq, VC_PROG_DATA, bad, 1);
        return;
    }
    p[0] = v;
    put32(p + 1, t->received);
    put32(p + 5, vc_store_free(s));
    reply(c, seq, VC_PROG_DATA | 0x80, p, sizeof p);
}

static void cmd_verify(vc_core *c, uint8_t seq, const uint8_t *pl, unsigned len)
{
    uint8_t p[16];
    vc_prog *t;
    if (len != 1) { error(c, VC_E_BAD_LENGTH, seq, VC_PROG_VERIFY, len, 1); return; }
    if (pl[0] >= VC_N_VALVES) { error(c, VC_E_BAD_VALUE, seq, VC_PROG_VERIFY, 0, 1); return; }
    t = vc_store_tail(&c->store[pl[0]]);
    if (!t) { error(c, VC_E_STATE, seq, VC_PROG_VERIFY, 0, 1); return; }
    p[0] = pl[0];
    p[1] = t->complete;
    put16(p + 2, t->crc);
    put32(p + 4, t->received);
    put32(p + 8, t->total);
    put32(p + 12, t->dec.pulses);
    reply(c, seq, VC_PROG_VERIFY | 0x80, p, sizeof p);
}

static void cmd_arm(vc_core *c, uint8_t seq, const uint8_t *pl, unsigned len)
{
    uint8_t p[6], mask;
    unsigned v;
    if (len != 1) { error(c, VC_E_BAD_LENGTH, seq, VC_ARM, len, 1); return; }
    mask = pl[0];
    if (mask == 0 || (mask >> VC_N_VALVES)) { error(c, VC_E_BAD_VALUE, seq, VC_ARM, 0, 1); return; }
    if (c->state == VC_FAULT || c->state == VC_ARMED ||
        (c->state == VC_PLAYING && c->queued_mask)) {
        error(c, VC_E_STATE, seq, VC_ARM, 0, 1);
        return;
    }
    for (v = 0; v < VC_N_VALVES; v++)
        if (((mask >> v) & 1u) && !ready(c, v, next_to_arm(c, v))) {
            error(c, VC_E_STATE, seq, VC_ARM, 0, 1);
            return;
        }
    for (v = 0; v < VC_N_VALVES; v++)
        if ((mask >> v) & 1u) next_to_arm(c, v)->locked = 1;
    put32(p + 2, play_length(c, mask, 1));
    if (c->state == VC_PLAYING) {
        c->queued_mask = mask;
    } else {
        c->armed_mask = mask;
        c->state = VC_ARMED;
    }
    p[0] = c->state;
    p[1] = mask;
    reply(c, seq, VC_ARM | 0x80, p, sizeof p);
}

static void cmd_abort(vc_core *c, uint8_t seq, unsigned len)
{
    uint8_t p[10];
    unsigned v;
    if (len != 0) { error(c, VC_E_BAD_LENGTH, seq, VC_ABORT, len, 1); return; }
    board_valves_off();                       /* first: every valve closed at once */
    p[0] = c->state;
    p[1] = c->fault;                          /* the fault it clears (0 if none) */
    for (v = 0; v < VC_N_VALVES; v++) {
        uint32_t e = (c->state == VC_PLAYING && ((c->armed_mask >> v) & 1u)) ?
                     c->store[v].rd.emitted : 0u;
        put32(p + 2 + 4 * v, e);
        if (c->state == VC_PLAYING) c->last_emitted[v] = e;
    }
    board_note(VC_NOTE_ABORT, c->plays, c->play_tick);
    clear_programs(c);
    c->state = VC_IDLE;
    c->fault = VC_FAULT_NONE;
    reply(c, seq, VC_ABORT | 0x80, p, sizeof p);
}

#ifdef VC_HOST_BUILD
static void cmd_trigger(vc_core *c, uint8_t seq, unsigned len)
{
    uint8_t p[1];
    if (len != 0) { error(c, VC_E_BAD_LENGTH, seq, VC_TRIGGER, len, 1); return; }
    if (!(c->state == VC_ARMED ||
          (c->state == VC_PLAYING && c->queued_mask && !c->early_trigger))) {
        error(c, VC_E_TRIGGER, seq, VC_TRIGGER, c->state, 1);
        return;
    }
    vc_trigger_edge(c);
    p[0] = c->state;
    reply(c, seq, VC_TRIGGER | 0x80, p, 1);
}

static void cmd_stall(vc_core *c, uint8_t seq, const uint8_t *pl, unsigned len)
{
    if (len != 4) { error(c, VC_E_BAD_LENGTH, seq, VC_STALL, len, 1); return; }
    reply(c, seq, VC_STALL | 0x80, pl, 4);
    board_stall(get32(pl));
}
#endif

static void dispatch(vc_core *c, uint32_t *lk, uint8_t seq, uint8_t type, const uint8_t *pl,
                     unsigned len)
{
    switch (type) {
    case VC_HELLO: cmd_hello(c, seq, pl, len); break;
    case VC_STATUS: cmd_status(c, seq, len); break;
    case VC_CONFIG: cmd_config(c, seq, pl, len); break;
    case VC_PROG_BEGIN: cmd_begin(c, seq, pl, len); break;
    case VC_PROG_DATA: cmd_data(c, lk, seq, pl, len); break;
    case VC_PROG_VERIFY: cmd_verify(c, seq, pl, len); break;
    case VC_ARM: cmd_arm(c, seq, pl, len); break;
    case VC_ABORT: cmd_abort(c, seq, len); break;
#ifdef VC_HOST_BUILD
    case VC_TRIGGER: cmd_trigger(c, seq, len); break;
    case VC_STALL: cmd_stall(c, seq, pl, len); break;
#endif
    default: error(c, VC_E_UNKNOWN_TYPE, seq, type, 0, 1); break;
    }
}

/* A command runs locked (it reads and changes what the tick shares), but for the bulk of
 * a PROG_DATA (cmd_data); its reply's CRC is summed after. */
static void handle_frame(vc_core *c, uint8_t seq, uint8_t type, const uint8_t *pl,
                         unsigned len)
{
    uint32_t lk;
    if (type != VC_HELLO && seq != c->expected) {
        if (c->have_cache && seq == (uint8_t)(c->expected - 1u)) {
            board_tx(c->cache, c->cache_len);     /* a repeat: answered, not executed */
            return;
        }
        error(c, VC_E_SEQUENCE, seq, type, 0, 0);
        return;
    }
    c->expected = (uint8_t)(seq + 1u);
    lk = board_lock();
    dispatch(c, &lk, seq, type, pl, len);
    board_unlock(lk);
    send_reply(c);
}

/* ------------------------------------------------------------------ receiving */

static void drop(vc_core *c, unsigned k)
{
    c->crc_n = 0;                             /* the frame's start moved */
    if (k >= c->flen) { c->flen = 0; return; }
    memmove(c->fb, c->fb + k, c->flen - k);
    c->flen = (uint16_t)(c->flen - k);
}

/* CRC of fb[2 .. 2 + n), carried on from the bytes summed before. When the board ran the
 * parser with interrupts off, summing a 247-byte frame at its last byte held them off
 * ~1 ms (a review's finding); summed as the bytes come, each byte adds one step (the
 * parser now runs unlocked: this keeps the main loop ahead of the line). */
static uint16_t frame_crc(vc_core *c, unsigned n)
{
    if (c->crc_n == 0 || c->crc_n > n) { c->crc_run = VC_CRC_INIT; c->crc_n = 0; }
    c->crc_run = vc_crc16_update(c->crc_run, c->fb + 2 + c->crc_n, n - c->crc_n);
    c->crc_n = (uint16_t)n;
    return c->crc_run;
}

/* Leading bytes of fb that start no frame (PROTOCOL.md 2: a frame starts A5 5A; a lone
 * A5 at the end may be one, unless the bytes are stale). Dropped in one move: dropped one
 * at a time, a 247-byte frame with a bad CRC moved ~30 000 bytes (~6 ms on the board, a
 * review's finding, then with interrupts off). */
static unsigned noise_run(const vc_core *c, int stale)
{
    unsigned k = 1;
    for (; k < c->flen; k++)
        if (c->fb[k] == VC_MARK0 && (k + 1u < c->flen ? c->fb[k + 1] == VC_MARK1 : !stale))
            break;
    return k;
}

static void flush_noise(vc_core *c)
{
    if (c->noise) {
        uint32_t n = c->noise;
        c->noise = 0;
        error(c, VC_E_NOISE, 0xFF, 0xFF, n, 0);
    }
}

/* Take every frame out of the buffer; stale: the bytes are older than the byte timeout,
 * so an unfinished frame is truncated. PROTOCOL.md 2. */
static void parse(vc_core *c, int stale)
{
    for (;;) {
        unsigned len;
        uint16_t crc;
        if (c->flen == 0) return;
        if (c->fb[0] != VC_MARK0 || (c->flen >= 2 && c->fb[1] != VC_MARK1) ||
            (c->flen == 1 && stale)) {
            unsigned k = noise_run(c, stale);
            c->noise += k;
            drop(c, k);
            continue;
        }
        if (c->flen == 1) return;
        flush_noise(c);
        if (c->flen < 3) {
            if (!stale) return;
            error(c, VC_E_TRUNCATED, 0xFF, 0xFF, c->flen, 0);
            drop(c, 2);
            continue;
        }
        len = c->fb[2];
        if (len > VC_MAX_PAYLOAD) {
            error(c, VC_E_OVERSIZE, c->flen > 3 ? c->fb[3] : 0xFF, c->flen > 4 ? c->fb[4] : 0xFF,
                  len, 0);
            drop(c, 2);
            continue;
        }
        if (c->flen < len + VC_FRAME_OVERHEAD) {
            if (!stale) {
                (void)frame_crc(c, c->flen - 2u < len + 3u ? c->flen - 2u : len + 3u);
                return;
            }
            error(c, VC_E_TRUNCATED, c->flen > 3 ? c->fb[3] : 0xFF, c->flen > 4 ? c->fb[4] : 0xFF,
                  c->flen, 0);
            drop(c, 2);
            continue;
        }
        crc = frame_crc(c, len + 3u);
        if (crc != get16(c->fb + 5 + len)) {
            error(c, VC_E_CRC, c->fb[3], c->fb[4], crc, 0);
            drop(c, 2);
            continue;
        }
        handle_frame(c, c->fb[3], c->fb[4], c->fb + 5, len);
        drop(c, len + VC_FRAME_OVERHEAD);
    }
}

void vc_rx(vc_core *c, const uint8_t *data, unsigned n, uint32_t now_ms)
{
    unsigned i;
    for (i = 0; i < n; i++) {
        c->fb[c->flen++] = data[i];           /* parse() keeps flen < VC_MAX_FRAME */
        parse(c, 0);
    }
    if (n) c->last_rx_ms = now_ms;
}

void vc_poll(vc_core *c, uint32_t now_ms)
{
    if ((c->flen || c->noise) && (uint32_t)(now_ms - c->last_rx_ms) >= VC_BYTE_TIMEOUT_MS) {
        parse(c, 1);
        flush_noise(c);
    }
}
