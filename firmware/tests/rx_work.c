/* A model of the LPC2148 board's work with interrupts off (`make rx-work`; BENCHMARKS.md,
 * "Valve firmware: work with interrupts off"). The core runs on the host with the loops
 * that depend on the bytes received counted: bytes moved (memmove, memcpy, memset, wrapped
 * with GNU ld's --wrap), bytes summed into CRCs (vc_crc16_update) and program bytes
 * validated (vc_store_check), and 64-bit divisions (vc_ticks_round past 2^32 us). At 48
 * MHz a byte moved takes ~9 cycles, one summed ~18, one validated ~80 and a division ~500
 * (libc.c's byte loops, crc16.c's table, vc_dec_byte and libgcc's __udivmoddi4, read off
 * the disassembly of `make arm`'s image; crc16.c's bit loop before took ~97). MAM stalls and
 * the straight-line code around the loops, a few hundred instructions at most, are not
 * counted.
 *
 * Two boards are modelled on the same run: "before", which ran every vc_rx (one byte) and
 * vc_poll call with interrupts off, and "now", which calls them with interrupts on while
 * the core masks them between board_lock() and board_unlock() (board.h). For each input it
 * prints the most work one interrupts-off region did under each. The inputs: a program
 * uploaded in 235-byte PROG_DATA frames, every other command, ABORT with programs queued,
 * bad bytes for an armed program (a FAULT), a 247-byte frame with a bad CRC, garbage of
 * start markers (pairs, and markers whose lengths all end on one byte), and a stream of
 * valid commands interleaved with garbage of every kind, run through a model of the
 * board's receive path (115 200 baud, the 512-byte ring the UART interrupt fills, a main
 * loop taking the counted cycles plus 200 a byte) that checks every valid command is
 * answered and no byte is lost.
 *
 * Fails (status 1) when a region now exceeds BOUND_CYCLES, the core takes no lock (the
 * board must then lock every call: "before"), a valid command goes unanswered or a byte is
 * lost, or when "before" stays within the bound (the model must see what the review
 * measured). */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "../core/board.h"
#include "../core/crc16.h"
#include "../core/valvectl.h"

#define CPU_HZ 48000000.0
#define CYC_MOVED 9.0
#define CYC_SUMMED 18.0
#define CYC_VALIDATED 80.0
#define CYC_DIVIDED 500.0           /* a 64-bit division by libgcc's loop */
#define CYC_PER_BYTE 200.0          /* the receive path's own work a byte (not counted) */
#define BOUND_CYCLES 500.0          /* ~10 us; the UART's FIFO holds 16 bytes (1.4 ms) */
#define LINE_CYCLES (CPU_HZ / 11520.0)    /* a byte at 115 200 baud 8N1 */
#define RX_RING 511u                /* board.c's rx_ring, one slot kept free */

typedef struct { unsigned long moved, summed, validated, divided; } work_t;
static work_t cur;

void *__real_memmove(void *d, const void *s, size_t n);
void *__wrap_memmove(void *d, const void *s, size_t n)
{
    cur.moved += n;
    return __real_memmove(d, s, n);
}
void *__real_memcpy(void *d, const void *s, size_t n);
void *__wrap_memcpy(void *d, const void *s, size_t n)
{
    cur.moved += n;
    return __real_memcpy(d, s, n);
}
void *__real_memset(void *d, int c, size_t n);
void *__wrap_memset(void *d, int c, size_t n)
{
    cur.moved += n;
    return __real_memset(d, c, n);
}
uint16_t __real_vc_crc16_update(uint16_t crc, const uint8_t *data, size_t n);
uint16_t __wrap_vc_crc16_update(uint16_t crc, const uint8_t *data, size_t n)
{
    cur.summed += n;
    return __real_vc_crc16_update(crc, data, n);
}
int __real_vc_store_check(const vc_prog *p, const uint8_t *d, uint32_t n, vc_dec *dec,
                          uint32_t *bad);
int __wrap_vc_store_check(const vc_prog *p, const uint8_t *d, uint32_t n, vc_dec *dec,
                          uint32_t *bad)
{
    cur.validated += n;
    return __real_vc_store_check(p, d, n, dec, bad);
}

uint32_t __real_vc_ticks_round(uint64_t us);
uint32_t __wrap_vc_ticks_round(uint64_t us)
{
    if (us >= 0xFFFFFFFFu - VC_TICK_US) cur.divided++;     /* program.c's 64-bit path */
    return __real_vc_ticks_round(us);
}

static double cycles(work_t w)
{
    return CYC_MOVED * (double)w.moved + CYC_SUMMED * (double)w.summed +
           CYC_VALIDATED * (double)w.validated + CYC_DIVIDED * (double)w.divided;
}
static work_t minus(work_t a, work_t b)
{
    work_t d;
    d.moved = a.moved - b.moved; d.summed = a.summed - b.summed;
    d.validated = a.validated - b.validated;
    d.divided = a.divided - b.divided;
    return d;
}

/* ------------------------------------------------------------------ board */
static vc_core core;
static uint32_t now_ms = 1000;
static int depth, in_tick;
static work_t at_lock, max_now, max_before;
static unsigned long regions;

static void keep_max(work_t *m, work_t w) { if (cycles(w) > cycles(*m)) *m = w; }

uint32_t board_lock(void)
{
    if (depth++ == 0 && !in_tick) at_lock = cur;
    return 0;
}
void board_unlock(uint32_t saved)
{
    (void)saved;
    if (--depth == 0 && !in_tick) { keep_max(&max_now, minus(cur, at_lock)); regions++; }
}

/* The replies sent that carry a command's result (SEQ, TYPE 0x80..0xDF: not ERROR, not an
 * event), in order; the core sends one frame a call. */
#define MAX_LOG 4096u
static uint8_t reply_seq[MAX_LOG], reply_type[MAX_LOG];
static unsigned replies;
void board_tx(const uint8_t *d, unsigned n)
{
    if (n >= 7 && d[0] == 0xA5 && d[1] == 0x5A && d[4] >= 0x80 && d[4] < 0xE0 &&
        replies < MAX_LOG) {
        reply_seq[replies] = d[3];
        reply_type[replies++] = d[4];
    }
}
void board_valve_pulse(unsigned v, uint16_t w, uint32_t t) { (void)v; (void)w; (void)t; }
void board_valves_off(void) {}
uint8_t board_outputs(void) { return 0; }
void board_note(int w, uint32_t a, uint32_t b) { (void)w; (void)a; (void)b; }
void board_stall(uint32_t ms) { (void)ms; }

/* One byte through the main loop: returns its whole work (the "before" region). */
static work_t rx_byte(uint8_t b)
{
    work_t w0 = cur, w;
    vc_rx(&core, &b, 1, now_ms);
    w = minus(cur, w0);
    keep_max(&max_before, w);
    return w;
}
static void poll_after(uint32_t ms)
{
    work_t w0 = cur;
    now_ms += ms;
    vc_poll(&core, now_ms);
    keep_max(&max_before, minus(cur, w0));
}
static void feed(const uint8_t *b, unsigned n)
{
    unsigned i;
    for (i = 0; i < n; i++) rx_byte(b[i]);
}
static void ticks(unsigned n)
{
    in_tick = 1;
    while (n--) { vc_tick(&core, 0); now_ms += 2; }
    in_tick = 0;
}

/* ------------------------------------------------------------------ inputs */
static uint8_t seq;
static unsigned frame(uint8_t *out, uint8_t s, uint8_t type, const uint8_t *p, unsigned len)
{
    uint16_t crc;
    unsigned i;
    out[0] = 0xA5; out[1] = 0x5A; out[2] = (uint8_t)len; out[3] = s; out[4] = type;
    for (i = 0; i < len; i++) out[5 + i] = p[i];
    crc = __real_vc_crc16_update(0xFFFF, out + 2, len + 3);
    out[5 + len] = (uint8_t)crc; out[6 + len] = (uint8_t)(crc >> 8);
    return len + 7;
}
/* A command; returns the TYPE of its reply (0: none, or an ERROR). */
static int command(uint8_t type, const uint8_t *p, unsigned len)
{
    uint8_t f[256];
    uint8_t s = seq++;
    unsigned r = replies;
    feed(f, frame(f, s, type, p, len));
    for (; r < replies; r++) if (reply_seq[r] == s) return reply_type[r];
    return 0;
}

static uint8_t prog[16384];
/* An FM program of n pulses (one piece), its bytes in prog; returns its length. */
static unsigned program(unsigned n)
{
    unsigned i, pos = 24, dur = 2000u * (n + 1u);
    memcpy(prog, "ICEV\x01\x00\x00\x00\xD0\x07\x00\x00\x01\x00\x00\x00", 16);
    prog[16] = (uint8_t)n; prog[17] = (uint8_t)(n >> 8); prog[18] = 0; prog[19] = 0;
    prog[20] = (uint8_t)dur; prog[21] = (uint8_t)(dur >> 8); prog[22] = (uint8_t)(dur >> 16);
    prog[23] = 0;
    for (i = 0; i < n; i++) { prog[pos++] = (uint8_t)i; prog[pos++] = (uint8_t)(i >> 8); }
    return pos;
}
/* PROG_BEGIN of len bytes and its first upto bytes (len: all); 1 if all were taken. */
static int upload_part(uint8_t valve, unsigned len, unsigned upto)
{
    uint8_t p[240];
    unsigned off, k;
    p[0] = valve; p[1] = 0; p[2] = (uint8_t)len; p[3] = (uint8_t)(len >> 8); p[4] = 0; p[5] = 0;
    if (command(VC_PROG_BEGIN, p, 6) != 0x90) return 0;
    for (off = 0; off < upto; off += k) {
        k = upto - off > 235 ? 235 : upto - off;
        p[0] = valve; p[1] = (uint8_t)off; p[2] = (uint8_t)(off >> 8); p[3] = 0; p[4] = 0;
        memcpy(p + 5, prog + off, k);
        if (command(VC_PROG_DATA, p, k + 5) != 0x91) return 0;
    }
    return 1;
}
static int upload(uint8_t valve, unsigned len) { return upload_part(valve, len, len); }

static int ok = 1;
static void report(const char *what)
{
    double b = cycles(max_before), n = cycles(max_now);
    printf("%-44s before %8.0f cycles (%6.3f ms) | now %5.0f cycles (%5.1f us): "
           "%lu moved, %lu summed, %lu validated, %lu long divisions\n", what, b,
           b / CPU_HZ * 1e3, n, n / CPU_HZ * 1e6, max_now.moved, max_now.summed,
           max_now.validated, max_now.divided);
    if (n > BOUND_CYCLES) ok = 0;
    memset(&max_now, 0, sizeof max_now);
    memset(&max_before, 0, sizeof max_before);
}
static double worst_before, worst_now;
static void keep_worst(void)
{
    if (cycles(max_before) > worst_before) worst_before = cycles(max_before);
    if (cycles(max_now) > worst_now) worst_now = cycles(max_now);
}
#define REPORT(what) do { keep_worst(); report(what); } while (0)

static void reset(void)
{
    in_tick = 1;
    vc_init(&core, VC_RESET_POWER);
    in_tick = 0;
    seq = 0;
    replies = 0;
    command(VC_HELLO, (const uint8_t *)"RDY\x01", 4);
    memset(&max_now, 0, sizeof max_now);
    memset(&max_before, 0, sizeof max_before);
}

/* Start markers whose frames all end on one byte: "A5 5A L" every 3 bytes, L = 240 - 3 k,
 * then one byte; each CRC fails and the next is summed from its start. */
static unsigned cascade(uint8_t *out)
{
    unsigned k, n = 0;
    for (k = 0; 3u * k + 3u <= 246u; k++) {
        out[n++] = 0xA5; out[n++] = 0x5A; out[n++] = (uint8_t)(240u - 3u * k);
    }
    while (n < 247u) out[n++] = 0x00;
    return n;
}

static uint64_t rng = 12345;
static uint32_t rnd(void)
{
    rng = rng * 6364136223846793005ULL + 1442695040888963407ULL;
    return (uint32_t)(rng >> 33);
}

/* The board's receive path on a stream: a byte arrives every LINE_CYCLES; the UART
 * interrupt (held off no longer than a region now) puts it in the ring, or loses it when
 * the ring is full; the main loop takes them one by one, each taking its counted work
 * plus CYC_PER_BYTE. Returns the bytes lost; *most: the most bytes the ring held. */
static unsigned long board_stream(const uint8_t *s, unsigned n, unsigned *most)
{
    static unsigned ring[RX_RING];
    unsigned head = 0, count = 0, next = 0;
    unsigned long lost = 0;
    double t = 0.0;                         /* the main loop's clock, cycles */
    *most = 0;
    for (;;) {
        work_t w;
        for (; next < n && (double)next * LINE_CYCLES <= t; next++) {
            if (count == RX_RING) { lost++; continue; }
            ring[(head + count++) % RX_RING] = next;
        }
        if (count > *most) *most = count;
        if (!count) {
            if (next >= n) break;
            t = (double)next * LINE_CYCLES;
            continue;
        }
        w = rx_byte(s[ring[head]]);
        head = (head + 1u) % RX_RING;
        count--;
        t += cycles(w) + CYC_PER_BYTE;
    }
    return lost;
}

int main(void)
{
    static uint8_t stream[200000];
    uint8_t f[256], p[240];
    static uint8_t want_seq[4096], want_type[4096];
    unsigned i, k, len, n, valid = 0, got = 0, behind, r;
    unsigned long lost;
    uint16_t crc;

    printf("most work in one interrupts-off region at 48 MHz (%.0f cycles a byte moved, %.0f "
           "summed, %.0f validated, %.0f a 64-bit division); before: each vc_rx / vc_poll "
           "call; now: each board_lock section (bound %.0f cycles)\n", CYC_MOVED, CYC_SUMMED,
           CYC_VALIDATED, CYC_DIVIDED, BOUND_CYCLES);

    reset();
    len = program(4000);
    if (!upload(0, len)) { printf("upload refused\n"); ok = 0; }
    REPORT("PROG_DATA frames (235 program bytes)");

    reset();
    upload(1, program(100));
    command(VC_STATUS, 0, 0);
    command(VC_PROG_VERIFY, (const uint8_t *)"\x01", 1);
    command(VC_CONFIG, (const uint8_t *)"\x00\x20\x03", 3);
    command(VC_ARM, (const uint8_t *)"\x02", 1);
    vc_trigger_edge(&core);
    ticks(20);
    command(VC_STATUS, 0, 0);                          /* while it plays */
    command(VC_HELLO, (const uint8_t *)"RDY\x01", 4);
    REPORT("HELLO STATUS CONFIG BEGIN VERIFY ARM");

    reset();                        /* 34 empty pieces of 131.072 s: past 2^32 us */
    memcpy(prog, "ICEV\x01\x00\x00\x00\xD0\x07\x00\x00\x22\x00\x00\x00", 16);
    for (i = 0; i < 34; i++) memcpy(prog + 16 + 8 * i, "\0\0\0\0\x00\x00\xD0\x07", 8);
    upload(0, 16 + 8 * 34);
    upload(1, 16 + 8 * 34);
    if (command(VC_ARM, (const uint8_t *)"\x03", 1) != 0xA0) { printf("ARM refused\n"); ok = 0; }
    REPORT("a 74-minute path each valve, and ARM");

    reset();
    for (i = 0; i < 4; i++) upload(0, program(1000));
    for (i = 0; i < 4; i++) upload(1, program(1000));
    memset(&max_now, 0, sizeof max_now); memset(&max_before, 0, sizeof max_before);
    command(VC_ABORT, 0, 0);
    REPORT("ABORT with 8 programs queued");

    reset();                        /* a streaming program armed, then bytes that break it */
    len = program(6100);
    upload_part(0, len, VC_STORE_BYTES - 100);
    command(VC_ARM, (const uint8_t *)"\x01", 1);
    memset(p, 0, sizeof p);
    k = VC_STORE_BYTES - 100;
    p[1] = (uint8_t)k; p[2] = (uint8_t)(k >> 8);
    memset(&max_now, 0, sizeof max_now); memset(&max_before, 0, sizeof max_before);
    if (command(VC_PROG_DATA, p, 105) || core.fault != VC_FAULT_BAD_STREAM) {
        printf("the bad bytes were taken\n");
        ok = 0;
    }
    REPORT("bad bytes for an armed program (FAULT)");

    reset();
    f[0] = 0xA5; f[1] = 0x5A; f[2] = 240; f[3] = 0; f[4] = 0x11;
    for (i = 5; i < 245; i++) f[i] = (uint8_t)(i * 7u + 3u) == 0xA5 ? 0 : (uint8_t)(i * 7u + 3u);
    crc = __real_vc_crc16_update(0xFFFF, f + 2, 243);
    f[245] = (uint8_t)crc; f[246] = (uint8_t)((crc >> 8) ^ 1u);
    feed(f, 247);
    REPORT("247-byte frame with a bad CRC");

    reset();
    for (i = 0; i < 2000; i++) { uint8_t b = i & 1 ? 0x5A : 0xA5; rx_byte(b); }
    poll_after(60);
    REPORT("2 000 bytes of start markers (A5 5A ...)");

    reset();
    len = cascade(f);
    feed(f, len);
    poll_after(60);
    REPORT("82 start markers whose frames end together");

    /* valid commands interleaved with garbage of every kind, through the board model */
    reset();
    for (n = 0, k = 0; k < 300 && n < sizeof stream - 2000; k++) {
        unsigned kind = k % 6, g;
        switch (kind) {
        case 0: for (g = 0; g < 400; g++) stream[n++] = g & 1 ? 0x5A : 0xA5; break;
        case 1: n += cascade(stream + n); break;
        case 2: for (g = 0; g < 300; g++) stream[n++] = (uint8_t)rnd(); break;
        case 3: n += frame(stream + n, 0x77, VC_STATUS, 0, 0) - 3; break;      /* cut */
        case 4: len = frame(stream + n, 0x66, VC_HELLO, (const uint8_t *)"RDY\x01", 4);
                stream[n + len - 1] ^= 0x10; n += len; break;                  /* bad CRC */
        default:
            for (g = 0; g < 60; g++) {
                stream[n++] = 0xA5; stream[n++] = 0x5A; stream[n++] = (uint8_t)rnd();
            }
            break;
        }
#define WANT(t) (want_seq[valid] = seq, want_type[valid++] = (uint8_t)((t) | 0x80))
        switch (k % 4) {
        case 0: WANT(VC_STATUS); n += frame(stream + n, seq++, VC_STATUS, 0, 0); break;
        case 1: WANT(VC_HELLO);
                n += frame(stream + n, seq++, VC_HELLO, (const uint8_t *)"RDY\x01", 4); break;
        case 2: p[0] = 0; p[1] = 0; p[2] = 24; p[3] = 1; p[4] = 0; p[5] = 0;   /* 280 bytes */
                WANT(VC_PROG_BEGIN); n += frame(stream + n, seq++, VC_PROG_BEGIN, p, 6); break;
        default: p[0] = 0; memset(p + 1, 0, 4); program(128); memcpy(p + 5, prog, 235);
                 WANT(VC_PROG_DATA); n += frame(stream + n, seq++, VC_PROG_DATA, p, 240);
                 WANT(VC_ABORT); n += frame(stream + n, seq++, VC_ABORT, 0, 0); break;
        }
#undef WANT
    }
    {
        r = replies;
        lost = board_stream(stream, n, &behind);
        poll_after(60);
        /* each command's own reply (its SEQ, its TYPE | 0x80), in order */
        for (i = 0; i < valid; i++) {
            unsigned q;
            for (q = r; q < replies; q++)
                if (reply_seq[q] == want_seq[i] && reply_type[q] == want_type[i]) break;
            if (q < replies) { got++; r = q + 1u; }
        }
        printf("stream of %u bytes: %u valid commands between garbage, %u answered; board "
               "model: %lu bytes lost, at most %u bytes waiting in the %u-byte ring\n", n, valid,
               got, lost, behind, RX_RING + 1u);
        if (got != valid || lost) ok = 0;
    }
    REPORT("that stream");

    if (!regions) {                         /* the board must then lock every call */
        printf("the core took no lock: a board must run each vc_rx / vc_poll call with "
               "interrupts off (before)\n");
        worst_now = worst_before;
    }
    printf("worst: before %.0f cycles (%.2f ms), now %.0f cycles (%.1f us), bound %.0f: %s\n",
           worst_before, worst_before / CPU_HZ * 1e3, worst_now, worst_now / CPU_HZ * 1e6,
           BOUND_CYCLES, ok && regions && worst_before > BOUND_CYCLES ? "ok" : "FAILED");
    return ok && regions && worst_before > BOUND_CYCLES ? 0 : 1;
}
