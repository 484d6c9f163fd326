/* C unit tests of the valve controller core (PROTOCOL.md), run by `make test`.
 * Plain checks with a tiny runner that prints "N passed, N failed". Expected values come
 * from the protocol text and the CRC catalogue, not from the core's code. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "../core/board.h"
#include "../core/crc16.h"
#include "../core/valvectl.h"

static int n_pass, n_fail, cur_fail;
#define CHECK(cond) do { if (!(cond)) { cur_fail = 1; \
    fprintf(stderr, "  %s:%d: CHECK(%s) failed\n", __FILE__, __LINE__, #cond); } } while (0)
#define CHECK_EQ(a, b) do { long long a_ = (long long)(a), b_ = (long long)(b); if (a_ != b_) { \
    cur_fail = 1; fprintf(stderr, "  %s:%d: %s == %lld, expected %s == %lld\n", __FILE__, \
    __LINE__, #a, a_, #b, b_); } } while (0)

/* ------------------------------------------------------------------ fake board */
static uint8_t txcap[1 << 18];
static size_t txn, txrd;
typedef struct { unsigned valve, width; unsigned long tick; } pulse_t;
static pulse_t pulses[70000];
static size_t npulses;
static unsigned offs, stalls;
static uint8_t open_mask;

void board_tx(const uint8_t *d, unsigned n)
{
    if (txn + n <= sizeof txcap) { memcpy(txcap + txn, d, n); txn += n; }
}
void board_valve_pulse(unsigned v, uint16_t w, uint32_t t)
{
    if (npulses < sizeof pulses / sizeof pulses[0]) {
        pulses[npulses].valve = v; pulses[npulses].width = w; pulses[npulses].tick = t;
        npulses++;
    }
    open_mask = (uint8_t)(open_mask | (1u << v));
}
void board_valves_off(void) { offs++; open_mask = 0; }
uint8_t board_outputs(void) { return open_mask; }
void board_note(int w, uint32_t a, uint32_t b) { (void)w; (void)a; (void)b; }
void board_stall(uint32_t ms) { (void)ms; stalls++; }
/* The tick interrupt, where a test wants one: isr(k) runs as the k-th lock a frame takes
 * is being taken (the core runs vc_rx unlocked and locks what the tick shares). */
static void (*isr)(unsigned k);
static unsigned locks_taken, lock_depth;
uint32_t board_lock(void)
{
    if (lock_depth++ == 0) {
        locks_taken++;
        if (isr) isr(locks_taken);
    }
    return 0;
}
void board_unlock(uint32_t saved) { (void)saved; lock_depth--; }

/* ------------------------------------------------------------------ link helpers */
typedef struct { uint8_t seq, type, len; uint8_t p[256]; } frame_t;
static vc_core C;
static uint8_t seq;
static uint32_t now;

/* Next frame the controller sent (independent decoder); 0 if none. */
static int next_frame(frame_t *f)
{
    while (txrd + 7 <= txn) {
        const uint8_t *b = txcap + txrd;
        unsigned len;
        if (b[0] != 0xA5 || b[1] != 0x5A) { txrd++; continue; }
        len = b[2];
        if (txrd + len + 7 > txn) return 0;
        if (vc_crc16_update(0xFFFF, b + 2, len + 3) != (uint16_t)(b[5 + len] | (b[6 + len] << 8))) {
            fprintf(stderr, "  controller sent a frame with a bad CRC\n");
            cur_fail = 1;
            txrd++;
            continue;
        }
        f->len = (uint8_t)len; f->seq = b[3]; f->type = b[4];
        memcpy(f->p, b + 5, len);
        txrd += len + 7;
        return 1;
    }
    return 0;
}

static unsigned make_frame(uint8_t *out, uint8_t s, uint8_t type, const uint8_t *p, unsigned len)
{
    uint16_t crc;
    out[0] = 0xA5; out[1] = 0x5A; out[2] = (uint8_t)len; out[3] = s; out[4] = type;
    if (len) memcpy(out + 5, p, len);
    crc = vc_crc16_update(0xFFFF, out + 2, len + 3);
    out[5 + len] = (uint8_t)crc; out[6 + len] = (uint8_t)(crc >> 8);
    return len + 7;
}

static void feed(const uint8_t *b, unsigned n) { vc_rx(&C, b, n, now); }

/* Send a command with sequence s; return the reply (skipping events). */
static frame_t send_seq(uint8_t s, uint8_t type, const void *p, unsigned len)
{
    uint8_t buf[300];
    frame_t f, r;
    memset(&r, 0, sizeof r);
    r.type = 0;
    feed(buf, make_frame(buf, s, type, p, len));
    while (next_frame(&f))
        if (f.type < 0xE0 || f.type > 0xEF) r = f;
    return r;
}
static frame_t cmd(uint8_t type, const void *p, unsigned len)
{
    return send_seq(seq++, type, p, len);
}
static unsigned u32(const uint8_t *p) { return p[0] | (p[1] << 8) | (p[2] << 16) | ((unsigned)p[3] << 24); }

static void reset(void)
{
    txn = txrd = 0; npulses = 0; offs = 0; stalls = 0; open_mask = 0; now = 1000;
    vc_init(&C, VC_RESET_POWER);
    seq = 7;
    {
        frame_t f = cmd(VC_HELLO, "RDY\x01", 4);
        CHECK_EQ(f.type, 0x81);
    }
}

/* A program in icefab.flow's binary layout. pieces: counts n[j], durations dur[j] (us),
 * ticks concatenated in ticks[], widths (PWM) in widths[]. */
static unsigned make_program(uint8_t *out, int pwm, unsigned np, const unsigned *n,
                             const unsigned *dur, const unsigned *ticks, const unsigned *widths)
{
    unsigned pos = 0, j, k, t = 0;
    memcpy(out, "ICEV", 4); pos = 4;
    out[pos++] = 1; out[pos++] = 0; out[pos++] = (uint8_t)pwm; out[pos++] = 0;
#define P32(v) do { unsigned v_ = (v); out[pos++] = (uint8_t)v_; out[pos++] = (uint8_t)(v_ >> 8); \
    out[pos++] = (uint8_t)(v_ >> 16); out[pos++] = (uint8_t)(v_ >> 24); } while (0)
    P32(2000); P32(np);
    for (j = 0; j < np; j++) {
        P32(n[j]); P32(dur[j]);
        for (k = 0; k < n[j]; k++) { out[pos++] = (uint8_t)ticks[t + k]; out[pos++] = (uint8_t)(ticks[t + k] >> 8); }
        if (pwm) for (k = 0; k < n[j]; k++) { out[pos++] = (uint8_t)widths[t + k]; out[pos++] = (uint8_t)(widths[t + k] >> 8); }
        t += n[j];
    }
#undef P32
    return pos;
}

/* Upload (begin + data chunks), return last reply type. */
static uint8_t upload(uint8_t valve, const uint8_t *prog, unsigned total, unsigned upto)
{
    uint8_t p[240];
    unsigned off = 0;
    frame_t f;
    p[0] = valve; p[1] = 0;
    p[2] = (uint8_t)total; p[3] = (uint8_t)(total >> 8); p[4] = (uint8_t)(total >> 16); p[5] = (uint8_t)(total >> 24);
    f = cmd(VC_PROG_BEGIN, p, 6);
    if (f.type != 0x90) return f.type;
    while (off < upto) {
        unsigned k = upto - off > 235 ? 235 : upto - off;
        p[0] = valve;
        p[1] = (uint8_t)off; p[2] = (uint8_t)(off >> 8); p[3] = (uint8_t)(off >> 16); p[4] = (uint8_t)(off >> 24);
        memcpy(p + 5, prog + off, k);
        f = cmd(VC_PROG_DATA, p, k + 5);
        if (f.type != 0x91) return f.type;
        off += k;
    }
    return f.type;
}

static frame_t status(void) { return cmd(VC_STATUS, 0, 0); }

static void run_ticks(unsigned n) { unsigned i; for (i = 0; i < n; i++) { vc_tick(&C, 0); now += 2; } }

/* ------------------------------------------------------------------ tests */

/* The polynomial's definition bit by bit, against crc16.c's table. */
static uint16_t crc_bits(uint16_t crc, uint8_t b)
{
    int i;
    crc ^= (uint16_t)(b << 8);
    for (i = 0; i < 8; i++)
        crc = (uint16_t)(crc & 0x8000u ? ((unsigned)crc << 1) ^ 0x1021u : (unsigned)crc << 1);
    return crc;
}

static void test_crc_catalogue(void)
{
    unsigned b, c;
    CHECK_EQ(vc_crc16_update(0xFFFF, (const uint8_t *)"123456789", 9), 0x29B1);
    for (c = 0; c < 0x10000u; c += 0x101u)
        for (b = 0; b < 256; b++) {
            uint8_t byte = (uint8_t)b;
            if (vc_crc16_update((uint16_t)c, &byte, 1) != crc_bits((uint16_t)c, byte) ||
                vc_crc16_byte((uint16_t)c, byte) != crc_bits((uint16_t)c, byte)) {
                CHECK_EQ(vc_crc16_byte((uint16_t)c, byte), crc_bits((uint16_t)c, byte));
                return;
            }
        }
}

static uint8_t prog[80000];

static void test_play_fm(void)
{
    /* two pieces: 3 pulses in 0.1 s, then 2 pulses (one shared tick) in 0.0503 s */
    unsigned n[2] = {3, 2}, dur[2] = {100000, 50300}, ticks[5] = {0, 10, 50, 5, 5};
    unsigned len = make_program(prog, 0, 2, n, dur, ticks, 0), crc;
    frame_t f;
    uint8_t arm = 1;
    reset();
    CHECK_EQ(upload(0, prog, len, len), 0x91);
    f = cmd(VC_PROG_VERIFY, "\x00", 1);
    CHECK_EQ(f.type, 0x92);
    crc = vc_crc16_update(0xFFFF, prog, len);
    CHECK_EQ(f.p[1], 1);
    CHECK_EQ(f.p[2] | (f.p[3] << 8), crc);
    CHECK_EQ(u32(f.p + 4), len);
    CHECK_EQ(u32(f.p + 12), 5);
    f = cmd(VC_ARM, &arm, 1);
    CHECK_EQ(f.type, 0xA0);
    CHECK_EQ(f.p[0], VC_ARMED);
    CHECK_EQ(u32(f.p + 2), 75);                       /* 150.3 ms -> 75 ticks (half up) */
    run_ticks(5);
    CHECK_EQ(npulses, 0);                             /* nothing before the trigger */
    vc_trigger_edge(&C);
    run_ticks(100);
    CHECK_EQ(npulses, 5);
    /* piece 1 starts at round(100000 / 2000) = 50 */
    CHECK_EQ(pulses[0].tick, 0); CHECK_EQ(pulses[1].tick, 10); CHECK_EQ(pulses[2].tick, 50);
    CHECK_EQ(pulses[3].tick, 55); CHECK_EQ(pulses[4].tick, 55);
    CHECK_EQ(pulses[0].width, 500);
    {   /* DONE event */
        size_t save = txrd;
        frame_t e;
        int seen = 0;
        txrd = 0;
        while (next_frame(&e))
            if (e.type == VC_EV_DONE) { seen = 1; CHECK_EQ(u32(e.p + 2), 75); CHECK_EQ(u32(e.p + 10), 5); }
        CHECK(seen);
        txrd = save;
        (void)save;
    }
    f = status();
    CHECK_EQ(f.p[0], VC_IDLE);
    CHECK_EQ(u32(f.p + 24 + 12), 5);
}

static void test_play_pwm_and_config(void)
{
    unsigned n[1] = {3}, dur[1] = {20000}, ticks[3] = {1, 2, 9}, widths[3] = {700, 1200, 3000};
    unsigned len = make_program(prog, 1, 1, n, dur, ticks, widths);
    uint8_t cfg[3] = {1, 0x20, 0x03};                 /* valve 1, 800 us (ignored in PWM) */
    uint8_t arm = 2;
    frame_t f;
    reset();
    f = cmd(VC_CONFIG, cfg, 3);
    CHECK_EQ(f.type, 0x83);
    CHECK_EQ(upload(1, prog, len, len), 0x91);
    CHECK_EQ(cmd(VC_ARM, &arm, 1).type, 0xA0);
    CHECK_EQ(cmd(VC_TRIGGER, 0, 0).type, 0xA2);
    run_ticks(20);
    CHECK_EQ(npulses, 3);
    CHECK_EQ(pulses[0].valve, 1);
    CHECK_EQ(pulses[0].tick, 1); CHECK_EQ(pulses[2].tick, 9);
    CHECK_EQ(pulses[0].width, 700); CHECK_EQ(pulses[1].width, 1200); CHECK_EQ(pulses[2].width, 3000);
    widths[1] = 0;                                    /* a zero width is refused */
    len = make_program(prog, 1, 1, n, dur, ticks, widths);
    CHECK_EQ(upload(1, prog, len, len), 0xFF);
}

static void test_sequence_rules(void)
{
    unsigned n[1] = {1}, dur[1] = {2000}, ticks[1] = {0};
    unsigned len = make_program(prog, 0, 1, n, dur, ticks, 0);
    uint8_t p[6] = {0, 0, 0, 0, 0, 0};
    frame_t f, g;
    reset();
    p[2] = (uint8_t)len;
    f = send_seq(seq, VC_PROG_BEGIN, p, 6);
    CHECK_EQ(f.type, 0x90);
    g = send_seq(seq, VC_PROG_BEGIN, p, 6);           /* repeat: same answer, not run twice */
    CHECK_EQ(g.type, 0x90);
    CHECK_EQ(g.seq, f.seq);
    CHECK(memcmp(f.p, g.p, f.len) == 0);
    seq++;
    f = status();
    CHECK_EQ(f.p[24], 1);                             /* one program queued, not two */
    f = send_seq((uint8_t)(seq + 5), VC_STATUS, 0, 0); /* out of order */
    CHECK_EQ(f.type, 0xFF);
    CHECK_EQ(f.p[0], VC_E_SEQUENCE);
    CHECK_EQ(f.p[2], seq);
    f = status();                                     /* the expected one still works */
    CHECK_EQ(f.type, 0x82);
    seq = 255;                                        /* wrap */
    CHECK_EQ(cmd(VC_HELLO, "RDY\x01", 4).type, 0x81);
    CHECK_EQ(status().type, 0x82);                    /* seq 0 after 255 */
}

static void test_frame_errors(void)
{
    uint8_t buf[300], b;
    frame_t f;
    unsigned k;
    reset();
    /* wrong CRC */
    k = make_frame(buf, seq, VC_STATUS, 0, 0);
    buf[k - 1] ^= 0x40;
    feed(buf, k);
    CHECK(next_frame(&f)); CHECK_EQ(f.type, 0xFF); CHECK_EQ(f.p[0], VC_E_CRC);
    /* oversized; the bad frame's 5 other bytes were noise, reported at the next marker */
    buf[0] = 0xA5; buf[1] = 0x5A; buf[2] = 241;
    feed(buf, 3);
    CHECK(next_frame(&f)); CHECK_EQ(f.p[0], VC_E_NOISE); CHECK_EQ(u32(f.p + 6), 5);
    CHECK(next_frame(&f)); CHECK_EQ(f.p[0], VC_E_OVERSIZE); CHECK_EQ(u32(f.p + 6), 241);
    /* noise (the LEN byte 241, then 5 letters): flushed by the byte timeout */
    feed((const uint8_t *)"hello", 5);
    CHECK(!next_frame(&f));
    now += 60; vc_poll(&C, now);
    CHECK(next_frame(&f)); CHECK_EQ(f.p[0], VC_E_NOISE); CHECK_EQ(u32(f.p + 6), 6);
    /* truncated */
    k = make_frame(buf, seq, VC_STATUS, 0, 0);
    feed(buf, k - 2);
    CHECK(!next_frame(&f));
    now += 49; vc_poll(&C, now);
    CHECK(!next_frame(&f));
    now += 2; vc_poll(&C, now);
    CHECK(next_frame(&f)); CHECK_EQ(f.p[0], VC_E_TRUNCATED);
    while (next_frame(&f)) { }
    /* a good frame right after garbage that holds a marker */
    buf[0] = 0xA5; buf[1] = 0x5A; buf[2] = 3; buf[3] = 0; buf[4] = 1;
    k = 5 + make_frame(buf + 5, seq, VC_STATUS, 0, 0);
    feed(buf, k);
    now += 60; vc_poll(&C, now);
    {
        int got_status = 0, got_err = 0;
        while (next_frame(&f)) { if (f.type == 0x82) got_status = 1; if (f.type == 0xFF) got_err = 1; }
        CHECK(got_status); CHECK(got_err);
        seq++;
    }
    /* unknown type, bad length, bad value */
    f = cmd(0x55, 0, 0); CHECK_EQ(f.p[0], VC_E_UNKNOWN_TYPE);
    f = cmd(VC_STATUS, "x", 1); CHECK_EQ(f.p[0], VC_E_BAD_LENGTH);
    b = 4; f = cmd(VC_ARM, &b, 1); CHECK_EQ(f.p[0], VC_E_BAD_VALUE);
    /* trigger with nothing armed: command and edge */
    f = cmd(VC_TRIGGER, 0, 0); CHECK_EQ(f.p[0], VC_E_TRIGGER);
    vc_trigger_edge(&C); vc_tick(&C, 0);
    CHECK(next_frame(&f)); CHECK_EQ(f.type, 0xFF); CHECK_EQ(f.p[0], VC_E_TRIGGER);
    CHECK_EQ(npulses, 0);
    CHECK_EQ(open_mask, 0);
}

static void test_program_violations(void)
{
    unsigned n[1] = {3}, dur[1] = {10000}, ticks[3] = {0, 4, 2};
    unsigned len;
    frame_t f;
    reset();
    len = make_program(prog, 0, 1, n, dur, ticks, 0);  /* decreasing ticks */
    CHECK_EQ(upload(0, prog, len, len), 0xFF);
    txrd = 0; { frame_t e; unsigned last = 0; while (next_frame(&e)) if (e.type == 0xFF) last = e.p[0] | (u32(e.p + 6) << 8); CHECK_EQ(last & 0xFF, VC_E_PROGRAM); CHECK_EQ(last >> 8, 16 + 8 + 4 + 1); }
    f = status(); CHECK_EQ(f.p[0], VC_IDLE); CHECK_EQ(f.p[24], 0);
    ticks[2] = 7;                                      /* tick 7 = 14 ms > 10 ms + one tick */
    len = make_program(prog, 0, 1, n, dur, ticks, 0);
    CHECK_EQ(upload(0, prog, len, len), 0xFF);
    ticks[2] = 6;                                      /* 10 ms + one tick: allowed */
    len = make_program(prog, 0, 1, n, dur, ticks, 0);
    CHECK_EQ(upload(0, prog, len, len), 0x91);
    CHECK_EQ(cmd(VC_ABORT, 0, 0).type, 0xA1);
    prog[0] = 'X';
    CHECK_EQ(upload(0, prog, len, len), 0xFF);         /* magic */
    len = make_program(prog, 0, 1, n, dur, ticks, 0);
    prog[8] = 0xE8; prog[9] = 0x03;                    /* tick 1000 us: not ours */
    CHECK_EQ(upload(0, prog, len, len), 0xFF);
    len = make_program(prog, 0, 1, n, dur, ticks, 0);
    prog[16] = 0x01; prog[17] = 0x40;                  /* 16 385 pulses */
    CHECK_EQ(upload(0, prog, len, len), 0xFF);
    len = make_program(prog, 0, 1, n, dur, ticks, 0);
    prog[20] = 0x01; prog[21] = 0x00; prog[22] = 0xD0; prog[23] = 0x07;  /* 131.072001 s */
    CHECK_EQ(upload(0, prog, len, len), 0xFF);
    len = make_program(prog, 0, 1, n, dur, ticks, 0);  /* announced one byte more than */
    CHECK_EQ(upload(0, prog, len + 1, len), 0xFF);     /* its layout: refused at its end */
    CHECK_EQ(upload(0, prog, len + 1, len - 1), 0x91); /* short of its total, so far fine */
    {
        uint8_t p[6] = {0, 0, 0, 0, 0, 0};
        frame_t g;
        p[0] = 0; p[1] = 0; p[2] = 0; p[3] = 0; p[4] = 0; p[5] = 0;
        g = cmd(VC_PROG_DATA, "\x00\x00\x00\x00\x00\x00", 6);   /* wrong offset */
        CHECK_EQ(g.p[0], VC_E_OFFSET);
        (void)p;
    }
    f = cmd(VC_PROG_VERIFY, "\x00", 1);
    CHECK_EQ(f.p[1], 0);                               /* not complete */
}

static void test_no_room_and_queue(void)
{
    static unsigned ticks[16384];
    unsigned n[1] = {3}, dur[1] = {10000}, t3[3] = {0, 1, 2}, i, len;
    frame_t f;
    reset();
    len = make_program(prog, 0, 1, n, dur, t3, 0);
    for (i = 0; i < 4; i++) CHECK_EQ(upload(0, prog, len, len), 0x91);
    CHECK_EQ(upload(0, prog, len, len), 0xFF);         /* fifth program */
    f = status(); CHECK_EQ(f.p[24], 4);
    CHECK_EQ(cmd(VC_ABORT, 0, 0).type, 0xA1);
    /* PWM piece larger than the store */
    for (i = 0; i < 4000; i++) ticks[i] = i / 8;
    n[0] = 4000; dur[0] = 131072000;
    len = make_program(prog, 1, 1, n, dur, ticks, ticks);
    CHECK_EQ(upload(0, prog, len, len), 0xFF);
    txrd = 0; { frame_t e; unsigned code = 0; while (next_frame(&e)) if (e.type == 0xFF) code = e.p[0]; CHECK_EQ(code, VC_E_NO_ROOM); }
    /* data beyond the free space */
    for (i = 0; i < 16384; i++) ticks[i] = (unsigned)(i * 4);
    n[0] = 16384;
    len = make_program(prog, 0, 1, n, dur, ticks, 0);
    CHECK_EQ(upload(0, prog, len, VC_STORE_BYTES - 100), 0x91);
    {
        uint8_t p[240];
        unsigned off = VC_STORE_BYTES - 100;
        p[0] = 0; p[1] = (uint8_t)off; p[2] = (uint8_t)(off >> 8); p[3] = 0; p[4] = 0;
        memcpy(p + 5, prog + off, 200);
        f = cmd(VC_PROG_DATA, p, 205);
        CHECK_EQ(f.type, 0xFF); CHECK_EQ(f.p[0], VC_E_NO_ROOM); CHECK_EQ(u32(f.p + 6), 100);
    }
}

/* A 16 384-pulse piece (32 kB) streams through the 12 kB store while it plays. */
static void test_streaming(void)
{
    static unsigned ticks[16384];
    unsigned n[1] = {16384}, dur[1] = {131072000}, i, len, off, guard = 0;
    uint8_t arm = 1, p[240];
    frame_t f;
    reset();
    for (i = 0; i < 16384; i++) ticks[i] = (unsigned)(i * 4);
    len = make_program(prog, 0, 1, n, dur, ticks, 0);
    off = VC_STORE_BYTES - 300;
    CHECK_EQ(upload(0, prog, len, off), 0x91);
    CHECK_EQ(cmd(VC_ARM, &arm, 1).p[0], VC_E_STATE);   /* not full yet: 300 free */
    p[0] = 0; p[1] = (uint8_t)off; p[2] = (uint8_t)(off >> 8); p[3] = 0; p[4] = 0;
    memcpy(p + 5, prog + off, 190);
    CHECK_EQ(cmd(VC_PROG_DATA, p, 195).type, 0x91);
    off += 190;
    f = cmd(VC_ARM, &arm, 1);
    CHECK_EQ(f.type, 0xA0);
    CHECK_EQ(u32(f.p + 2), 0xFFFFFFFFu);               /* length unknown while streaming */
    vc_trigger_edge(&C);
    while (C.state == VC_PLAYING || C.state == VC_ARMED) {
        run_ticks(50);
        while (off < len && vc_store_free(&C.store[0]) >= 235) {
            unsigned k = len - off > 235 ? 235 : len - off;
            p[1] = (uint8_t)off; p[2] = (uint8_t)(off >> 8); p[3] = (uint8_t)(off >> 16); p[4] = 0;
            memcpy(p + 5, prog + off, k);
            f = cmd(VC_PROG_DATA, p, k + 5);
            CHECK_EQ(f.type, 0x91);
            off += k;
        }
        if (++guard > 10000) break;
    }
    CHECK_EQ(off, len);
    CHECK_EQ(npulses, 16384);
    CHECK_EQ(pulses[16383].tick, 16383u * 4u);
    f = status();
    CHECK_EQ(f.p[0], VC_IDLE); CHECK_EQ(f.p[1], 0);
    CHECK_EQ(u32(f.p + 16), 65536);
}

/* Stream the rest of prog[off..len) while the store has room for a whole chunk. */
static unsigned top_up(unsigned off, unsigned len)
{
    uint8_t p[240];
    while (off < len && vc_store_free(&C.store[0]) > 0) {
        unsigned k = len - off > 235 ? 235 : len - off;
        if (k > vc_store_free(&C.store[0])) k = vc_store_free(&C.store[0]);
        p[0] = 0; p[1] = (uint8_t)off; p[2] = (uint8_t)(off >> 8); p[3] = (uint8_t)(off >> 16);
        p[4] = 0;
        memcpy(p + 5, prog + off, k);
        CHECK_EQ(cmd(VC_PROG_DATA, p, k + 5).type, 0x91);
        off += k;
    }
    return off;
}

/* After a reset: valve 0's program of len bytes begun, sent up to upto (as far as the
 * store takes it), armed and triggered; returns the bytes sent. */
static unsigned start_streaming(unsigned len, unsigned upto)
{
    uint8_t arm = 1;
    unsigned off;
    reset();
    CHECK_EQ(cmd(VC_PROG_BEGIN, (uint8_t[]){0, 0, (uint8_t)len, (uint8_t)(len >> 8),
                 (uint8_t)(len >> 16), 0}, 6).type, 0x90);
    off = top_up(0, upto);
    CHECK_EQ(cmd(VC_ARM, &arm, 1).type, 0xA0);
    vc_trigger_edge(&C);
    return off;
}

/* Three PWM pieces of 3069 pulses (the most a PWM piece may hold: 4 n + 10 <= 12 288), a
 * pulse every 2 ticks and none missing between pieces, streamed by a PC that tops the
 * store up every third tick (a driver polling every 5 ms). The reader wanted a piece
 * whole at its start, beside the last piece's widths (freed only then): this underran at
 * the first piece's end (a review found it at 2 048 pulses a piece); tick i and width i
 * are all a pulse needs, and with 3069 they fit beside the last piece's widths before it
 * ends. Then the same program with the PC gone silent: the underrun comes when a missing
 * pulse is due (its tick, or the piece's start when even that is missing), not before;
 * and a piece of 3070 pulses is refused (NO_ROOM). */
static void test_streaming_pwm_pieces(void)
{
    static unsigned ticks[3 * 3069], widths[3 * 3069];
    unsigned n[3] = {3069, 3069, 3069}, dur[3], i, len, off, t, k, stop_at;
    frame_t f;
    for (i = 0; i < 3; i++) dur[i] = 3069u * 2u * 2000u;
    for (i = 0; i < 3 * 3069; i++) { ticks[i] = (i % 3069) * 2u; widths[i] = 500u + i % 7u; }
    len = make_program(prog, 1, 3, n, dur, ticks, widths);
    off = start_streaming(len, len);
    for (t = 0; t < 3u * 6138u + 10u && C.state != VC_IDLE; t++) {
        if (t % 3u == 0) off = top_up(off, len);
        vc_tick(&C, 0);
        now += 2;
    }
    f = status();
    CHECK_EQ(f.p[0], VC_IDLE); CHECK_EQ(f.p[1], 0);
    CHECK_EQ(off, len);
    CHECK_EQ(npulses, 3 * 3069);
    for (k = 0; k < 3 * 3069; k += 1021) {
        CHECK_EQ(pulses[k].tick, (k / 3069u) * 6138u + (k % 3069u) * 2u);
        CHECK_EQ(pulses[k].width, widths[k]);
    }
    /* the PC stops sending within the second piece's header, or after its ticks and
     * 1 000 of its widths */
    for (stop_at = 0; stop_at < 2; stop_at++) {
        unsigned upto = 16u + (8u + 4u * 3069u) + (stop_at ? 8u + 2u * 3069u + 2000u : 4u);
        unsigned due = stop_at ? 6138u + 1000u * 2u : 6138u;
        off = start_streaming(len, upto);
        for (t = 0; t < 20000u && (t == 0 || C.state == VC_PLAYING); t++) {
            off = top_up(off, upto);
            vc_tick(&C, 0);
            now += 2;
        }
        f = status();
        CHECK_EQ(f.p[0], VC_FAULT); CHECK_EQ(f.p[1], VC_FAULT_UNDERRUN);
        CHECK_EQ(t, due + 1u);     /* the fault at play tick `due`, not sooner */
    }
    /* one pulse more: refused whole */
    n[0] = 3070; dur[0] = 3070u * 2u * 2000u;
    for (i = 0; i < 3070; i++) { ticks[i] = i * 2u; widths[i] = 500u; }
    len = make_program(prog, 1, 1, n, dur, ticks, widths);
    reset();
    CHECK_EQ(upload(0, prog, len, len), 0xFF);
}

static void test_underrun_fault(void)
{
    static unsigned ticks[16384];
    unsigned n[1] = {16384}, dur[1] = {131072000}, i, len;
    uint8_t arm = 1;
    frame_t f;
    reset();
    for (i = 0; i < 16384; i++) ticks[i] = i;
    len = make_program(prog, 0, 1, n, dur, ticks, 0);
    CHECK_EQ(upload(0, prog, len, VC_STORE_BYTES - 10), 0x91);
    CHECK_EQ(cmd(VC_ARM, &arm, 1).type, 0xA0);
    vc_trigger_edge(&C);
    run_ticks(8000);
    f = status();
    CHECK_EQ(f.p[0], VC_FAULT); CHECK_EQ(f.p[1], VC_FAULT_UNDERRUN);
    CHECK(offs > 0); CHECK_EQ(open_mask, 0);
    CHECK_EQ(cmd(VC_PROG_BEGIN, "\x00\x00\x20\x00\x00\x00", 6).p[0], VC_E_STATE);
    f = cmd(VC_ABORT, 0, 0);
    CHECK_EQ(f.p[0], VC_FAULT); CHECK_EQ(f.p[1], VC_FAULT_UNDERRUN);
    f = status();
    CHECK_EQ(f.p[0], VC_IDLE); CHECK_EQ(f.p[1], VC_FAULT_UNDERRUN);  /* last fault shown */
}

static void test_abort_while_playing(void)
{
    unsigned n[1] = {4}, dur[1] = {1000000}, ticks[4] = {0, 100, 200, 300}, len;
    uint8_t arm = 1;
    frame_t f;
    reset();
    len = make_program(prog, 0, 1, n, dur, ticks, 0);
    CHECK_EQ(upload(0, prog, len, len), 0x91);
    CHECK_EQ(cmd(VC_ARM, &arm, 1).type, 0xA0);
    vc_trigger_edge(&C);
    run_ticks(150);
    CHECK_EQ(npulses, 2);
    offs = 0;
    f = cmd(VC_ABORT, 0, 0);
    CHECK_EQ(f.type, 0xA1); CHECK_EQ(f.p[0], VC_PLAYING); CHECK_EQ(u32(f.p + 2), 2);
    CHECK_EQ(offs, 1); CHECK_EQ(open_mask, 0);
    run_ticks(300);
    CHECK_EQ(npulses, 2);
    CHECK_EQ(status().p[0], VC_IDLE);
}

static void test_watchdog_reset(void)
{
    frame_t f;
    txn = txrd = 0;
    vc_init(&C, VC_RESET_WATCHDOG);
    CHECK(next_frame(&f)); CHECK_EQ(f.type, VC_EV_BOOT); CHECK_EQ(f.p[0], 1);
    seq = 0;
    f = status();
    CHECK_EQ(f.p[0], VC_FAULT); CHECK_EQ(f.p[1], VC_FAULT_WATCHDOG);
    f = cmd(VC_ARM, "\x01", 1); CHECK_EQ(f.p[0], VC_E_STATE);
    CHECK_EQ(cmd(VC_ABORT, 0, 0).type, 0xA1);
    CHECK_EQ(status().p[0], VC_IDLE);
}

/* The next path uploads and arms while one plays; its early trigger starts it on the
 * tick the first one ends: no gap. */
static void test_queued_arm_no_gap(void)
{
    unsigned n[1] = {2}, dur[1] = {20000}, ticks[2] = {0, 9}, len;
    unsigned n2[1] = {2}, t2[2] = {0, 3};
    static uint8_t prog2[100];
    unsigned len2;
    uint8_t arm0 = 1, arm1 = 2;
    frame_t f;
    reset();
    len = make_program(prog, 0, 1, n, dur, ticks, 0);
    len2 = make_program(prog2, 0, 1, n2, dur, t2, 0);
    CHECK_EQ(upload(0, prog, len, len), 0x91);
    CHECK_EQ(cmd(VC_ARM, &arm0, 1).type, 0xA0);
    vc_trigger_edge(&C);
    run_ticks(3);
    CHECK_EQ(upload(1, prog2, len2, len2), 0x91);
    f = cmd(VC_ARM, &arm1, 1);
    CHECK_EQ(f.type, 0xA0); CHECK_EQ(f.p[0], VC_PLAYING); CHECK_EQ(u32(f.p + 2), 10);
    CHECK_EQ(cmd(VC_TRIGGER, 0, 0).type, 0xA2);       /* early: the robot is already there */
    run_ticks(30);
    CHECK_EQ(npulses, 4);
    CHECK_EQ(pulses[2].valve, 1);
    CHECK_EQ(pulses[2].tick, 0);
    /* play 1 ended at its tick 10 = the 11th tick after its trigger; play 2's tick 0 is
     * that same tick */
    CHECK_EQ(C.plays, 2);
    CHECK_EQ(status().p[0], VC_IDLE);
}

/* An early trigger's delay (PROTOCOL.md 7: "its delay counts as late ticks") is the ticks
 * between the tick that would have started the play had it been armed (the first tick
 * after the edge: play tick 0, section 7) and the tick that did start it. Play 1 lasts 10
 * ticks: its end is handled at the tick of its play tick 10. An edge before play 1's tick
 * 3 waits for ticks 3..10: 7 ticks; an edge before its tick 10: none. */
static void test_early_trigger_delay(void)
{
    unsigned n[1] = {2}, dur[1] = {20000}, ticks[2] = {0, 9}, len;
    unsigned n2[1] = {2}, t2[2] = {0, 3}, edge_before, expect, seen;
    static uint8_t prog2[100];
    unsigned len2;
    uint8_t arm0 = 1, arm1 = 2;
    frame_t f, e;
    len = make_program(prog, 0, 1, n, dur, ticks, 0);
    len2 = make_program(prog2, 0, 1, n2, dur, t2, 0);
    for (edge_before = 3; edge_before <= 10; edge_before += 7) {
        expect = 10u - edge_before;
        reset();
        CHECK_EQ(upload(0, prog, len, len), 0x91);
        CHECK_EQ(cmd(VC_ARM, &arm0, 1).type, 0xA0);
        vc_trigger_edge(&C);
        run_ticks(edge_before);                        /* play ticks 0 .. edge_before-1 */
        CHECK_EQ(upload(1, prog2, len2, len2), 0x91);
        CHECK_EQ(cmd(VC_ARM, &arm1, 1).p[0], VC_PLAYING);
        vc_trigger_edge(&C);                           /* the robot's edge, early */
        run_ticks(10u - edge_before + 1u);             /* through play 1's tick 10 */
        CHECK_EQ(C.plays, 2);
        CHECK_EQ(npulses, 3);                          /* play 2's tick 0 pulse: this tick */
        f = status();
        CHECK_EQ(f.p[0], VC_PLAYING);
        CHECK_EQ(u32(f.p + 12), expect);
        run_ticks(20);
        txrd = 0;
        seen = 0;
        while (next_frame(&e))
            if (e.type == VC_EV_DONE && (e.p[0] | (e.p[1] << 8)) == 2) {
                seen++;
                CHECK_EQ(u32(e.p + 6), expect);            /* DONE's late ticks */
            }
        CHECK_EQ(seen, 1);
    }
}

/* A tick handled late counts for every play it is a tick of (PROTOCOL.md 7): a play that
 * an early trigger starts on the tick the last one ends has that tick as its tick 0, as a
 * play started from ARMED does (its tick 0 late: 1 late tick). */
static void test_late_tick_zero_of_queued_play(void)
{
    unsigned n[1] = {2}, dur[1] = {20000}, ticks[2] = {0, 9}, len;
    unsigned n2[1] = {2}, t2[2] = {0, 3}, len2, i;
    static uint8_t prog2[100];
    uint8_t arm0 = 1, arm1 = 2;
    frame_t e;
    unsigned late[3] = {0, 0, 0};
    len = make_program(prog, 0, 1, n, dur, ticks, 0);
    len2 = make_program(prog2, 0, 1, n2, dur, t2, 0);
    reset();
    CHECK_EQ(upload(0, prog, len, len), 0x91);
    CHECK_EQ(cmd(VC_ARM, &arm0, 1).type, 0xA0);
    vc_trigger_edge(&C);
    vc_tick(&C, 1);                                    /* play 1's tick 0, late */
    run_ticks(9);                                      /* its ticks 1..9 */
    CHECK_EQ(upload(1, prog2, len2, len2), 0x91);
    CHECK_EQ(cmd(VC_ARM, &arm1, 1).p[0], VC_PLAYING);
    vc_trigger_edge(&C);                               /* taken at play 1's last tick */
    vc_tick(&C, 1);                                    /* play 1's tick 10 = play 2's tick 0 */
    CHECK_EQ(C.plays, 2);
    for (i = 0; i < 20; i++) vc_tick(&C, 0);
    txrd = 0;
    while (next_frame(&e))
        if (e.type == VC_EV_DONE && (e.p[0] | (e.p[1] << 8)) <= 2)
            late[e.p[0] | (e.p[1] << 8)] = u32(e.p + 6) + 100u;
    CHECK_EQ(late[1], 102);                            /* its ticks 0 and 10 */
    CHECK_EQ(late[2], 101);                            /* its tick 0, no wait */
}

/* ABORT's "fault before" is the fault this ABORT clears (state before FAULT), not the
 * last fault STATUS shows: a second ABORT cleared none. */
static void test_abort_fault_before(void)
{
    frame_t f;
    txn = txrd = 0;
    vc_init(&C, VC_RESET_WATCHDOG);
    seq = 0;
    f = cmd(VC_ABORT, 0, 0);
    CHECK_EQ(f.p[0], VC_FAULT); CHECK_EQ(f.p[1], VC_FAULT_WATCHDOG);
    f = cmd(VC_ABORT, 0, 0);                           /* nothing between */
    CHECK_EQ(f.p[0], VC_IDLE); CHECK_EQ(f.p[1], VC_FAULT_NONE);
    CHECK_EQ(status().p[1], VC_FAULT_WATCHDOG);        /* STATUS: the last fault */
    vc_fault(&C, VC_FAULT_INTERNAL);                   /* a fault between */
    f = cmd(VC_ABORT, 0, 0);
    CHECK_EQ(f.p[0], VC_FAULT); CHECK_EQ(f.p[1], VC_FAULT_INTERNAL);
    f = cmd(VC_ABORT, 0, 0);
    CHECK_EQ(f.p[0], VC_IDLE); CHECK_EQ(f.p[1], VC_FAULT_NONE);
}

/* PROG_DATA is validated, summed and copied into the store with the tick free to run (the
 * board's interrupts on), between its two locks. A tick there: (1) consuming the bytes of
 * the program that streams while it plays: every pulse still comes on its tick; (2)
 * faulting UNDERRUN: the frame's bytes are not taken (STATE error), the store stays
 * empty, every valve closed. */
static unsigned isr_ticks;
static void tick_at_second_lock(unsigned k)
{
    if (k != 2) return;
    isr_ticks++;
    isr = 0;                                           /* one interrupt per frame */
    vc_tick(&C, 0);
    now += 2;
    isr = tick_at_second_lock;
}

static void tick_until_fault(unsigned k)
{
    if (k != 2) return;
    isr = 0;
    while (C.state == VC_PLAYING) { vc_tick(&C, 0); now += 2; }
}

static void test_tick_inside_prog_data(void)
{
    static unsigned ticks[16384];
    unsigned n[1] = {16384}, dur[1] = {131072000}, i, len, off, t;
    uint8_t p[240];
    frame_t f;
    for (i = 0; i < 16384; i++) ticks[i] = i * 4u;
    len = make_program(prog, 0, 1, n, dur, ticks, 0);
    off = start_streaming(len, len);
    isr_ticks = 0;
    for (t = 0; (t == 0 || C.state == VC_PLAYING) && t < 70000u; t++) {
        locks_taken = 0;
        isr = tick_at_second_lock;
        off = top_up(off, len);                        /* one tick inside each PROG_DATA */
        isr = 0;
        vc_tick(&C, 0);
        now += 2;
    }
    f = status();
    CHECK_EQ(f.p[0], VC_IDLE); CHECK_EQ(f.p[1], 0);
    CHECK_EQ(off, len);
    CHECK_EQ(npulses, 16384);
    CHECK(isr_ticks > 80);                             /* a tick inside every PROG_DATA */
    for (i = 0; i < 16384; i += 1000) CHECK_EQ(pulses[i].tick, i * 4u);
    /* the PC falls behind: the underrun comes inside the frame that was to fill the gap */
    off = start_streaming(len, VC_STORE_BYTES - 200);
    while (C.store[0].used > 8u) { vc_tick(&C, 0); now += 2; }
    CHECK_EQ(C.state, VC_PLAYING);
    p[0] = 0; p[1] = (uint8_t)off; p[2] = (uint8_t)(off >> 8); p[3] = 0; p[4] = 0;
    memcpy(p + 5, prog + off, 200);
    locks_taken = 0;
    isr = tick_until_fault;
    f = cmd(VC_PROG_DATA, p, 205);
    isr = 0;
    CHECK_EQ(f.type, 0xFF); CHECK_EQ(f.p[0], VC_E_STATE);
    CHECK_EQ(f.p[4], VC_FAULT); CHECK_EQ(f.p[5], VC_FAULT_UNDERRUN);
    CHECK_EQ(C.store[0].count, 0); CHECK_EQ(C.store[0].used, 0);
    CHECK_EQ(open_mask, 0);
    f = cmd(VC_ABORT, 0, 0);
    CHECK_EQ(f.type, 0xA1);
    CHECK_EQ(upload(0, prog, len, 2000), 0x91);        /* the store takes programs again */
    CHECK_EQ(cmd(VC_PROG_VERIFY, "\x00", 1).p[4], 0xD0);
}

static void test_stall_command(void)
{
    frame_t f;
    reset();
    f = cmd(VC_STALL, "\x10\x27\x00\x00", 4);
    CHECK_EQ(f.type, 0xF0);
    CHECK_EQ(stalls, 1);
}

typedef void (*test_fn)(void);
static const struct { const char *name; test_fn fn; } TESTS[] = {
    {"crc_catalogue", test_crc_catalogue},
    {"play_fm", test_play_fm},
    {"play_pwm_and_config", test_play_pwm_and_config},
    {"sequence_rules", test_sequence_rules},
    {"frame_errors", test_frame_errors},
    {"program_violations", test_program_violations},
    {"no_room_and_queue", test_no_room_and_queue},
    {"streaming", test_streaming},
    {"streaming_pwm_pieces", test_streaming_pwm_pieces},
    {"underrun_fault", test_underrun_fault},
    {"abort_while_playing", test_abort_while_playing},
    {"watchdog_reset", test_watchdog_reset},
    {"queued_arm_no_gap", test_queued_arm_no_gap},
    {"early_trigger_delay", test_early_trigger_delay},
    {"abort_fault_before", test_abort_fault_before},
    {"late_tick_zero_of_queued_play", test_late_tick_zero_of_queued_play},
    {"stall_command", test_stall_command},
    {"tick_inside_prog_data", test_tick_inside_prog_data},
};

int main(void)
{
    unsigned i;
    for (i = 0; i < sizeof TESTS / sizeof TESTS[0]; i++) {
        cur_fail = 0;
        TESTS[i].fn();
        if (cur_fail) { n_fail++; printf("FAIL %s\n", TESTS[i].name); }
        else { n_pass++; printf("ok   %s\n", TESTS[i].name); }
    }
    printf("%d passed, %d failed\n", n_pass, n_fail);
    return n_fail ? 1 : 0;
}
