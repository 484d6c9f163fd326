/* Randomised fuzz of the valve controller core, compiled with the system C compiler and
 * AddressSanitizer / UndefinedBehaviorSanitizer (`make fuzz`; `build/fuzz_core N SEED`).
 *
 * Millions of inputs straight into the core (no pty): random bytes, good frames with
 * random damage (bit flips, cuts, oversized LEN), good frames of every type with random
 * payloads and sequence numbers, real programs with random damage, ticks and trigger edges
 * in between. After every input the byte timeout is allowed to pass, and it checks: some
 * frame was sent back for it (every input answered), the state machine's invariants hold,
 * and whenever nothing plays every valve is closed. A sanitizer report or a failed check
 * ends the run with status 1. Prints "N passed, N failed". */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "../core/board.h"
#include "../core/crc16.h"
#include "../core/valvectl.h"

static vc_core C;
static unsigned long tx_frames, tx_bytes, pulses;
static uint64_t now_us;                  /* controller time */
static uint64_t off_us[VC_N_VALVES];

void board_tx(const uint8_t *d, unsigned n)
{
    unsigned i;
    for (i = 0; i + 1 < n; i++) if (d[i] == 0xA5 && d[i + 1] == 0x5A) tx_frames++;
    tx_bytes += n;
}
void board_valve_pulse(unsigned v, uint16_t w, uint32_t t)
{
    (void)t;
    if (v < VC_N_VALVES && now_us + w > off_us[v]) off_us[v] = now_us + w;
    pulses++;
}
void board_valves_off(void) { off_us[0] = off_us[1] = 0; }
uint8_t board_outputs(void)
{
    return (uint8_t)((now_us < off_us[0] ? 1u : 0u) | (now_us < off_us[1] ? 2u : 0u));
}
void board_note(int w, uint32_t a, uint32_t b) { (void)w; (void)a; (void)b; }
void board_stall(uint32_t ms) { (void)ms; }

static uint32_t rn(uint32_t n);
static int lock_depth, in_tick;
static unsigned long isr_ticks;
static void tick(int late)
{
    in_tick = 1;
    now_us += 2000;
    vc_tick(&C, late);
    in_tick = 0;
}
/* The core runs vc_rx / vc_poll unlocked and locks what the tick shares (board.h): the
 * tick interrupt, which may come anywhere outside a lock, comes here at random just before
 * a lock is taken (all that runs unlocked since the last one touches only the link's own
 * fields, so this is every interleaving that matters). */
uint32_t board_lock(void)
{
    if (lock_depth++ == 0 && !in_tick && rn(6) == 0) { tick(0); isr_ticks++; }
    return 0;
}
void board_unlock(uint32_t saved) { (void)saved; lock_depth--; }

static uint64_t rng_state;
static uint32_t rnd(void)
{
    rng_state = rng_state * 6364136223846793005ULL + 1442695040888963407ULL;
    return (uint32_t)(rng_state >> 33);
}
static uint32_t rn(uint32_t n) { return n ? rnd() % n : 0; }

static unsigned frame(uint8_t *out, uint8_t seq, uint8_t type, const uint8_t *p, unsigned len)
{
    uint16_t crc;
    out[0] = 0xA5; out[1] = 0x5A; out[2] = (uint8_t)len; out[3] = seq; out[4] = type;
    if (len) memcpy(out + 5, p, len);
    crc = vc_crc16_update(0xFFFF, out + 2, len + 3);
    out[5 + len] = (uint8_t)crc; out[6 + len] = (uint8_t)(crc >> 8);
    return len + 7;
}

/* A valid FM or small PWM program; returns its length. */
static unsigned program(uint8_t *out)
{
    unsigned pos = 16, np = 1 + rn(3), j, k, pwm = rn(4) == 0;
    memcpy(out, "ICEV\x01\x00", 6);
    out[6] = (uint8_t)pwm; out[7] = 0;
    out[8] = 0xD0; out[9] = 0x07; out[10] = 0; out[11] = 0;
    out[12] = (uint8_t)np; out[13] = out[14] = out[15] = 0;
    for (j = 0; j < np; j++) {
        unsigned n = rn(40), dur = 1 + rn(60), t = 0;
        uint32_t dus = dur * 2000u;
        memcpy(out + pos, &n, 4); memcpy(out + pos + 4, &dus, 4);   /* host is little-endian */
        pos += 8;
        for (k = 0; k < n; k++) {
            t += rn(3);
            if (t > dur) t = dur;
            out[pos++] = (uint8_t)t; out[pos++] = (uint8_t)(t >> 8);
        }
        if (pwm) for (k = 0; k < n; k++) { unsigned w = 1 + rn(3000); out[pos++] = (uint8_t)w; out[pos++] = (uint8_t)(w >> 8); }
    }
    return pos;
}

static int check(unsigned long i, const char *what)
{
    unsigned v;
    int bad = 0;
    if (C.state > VC_FAULT) bad = 1;
    for (v = 0; v < VC_N_VALVES; v++) {
        if (C.store[v].used > VC_STORE_BYTES || C.store[v].count > VC_QUEUE) bad = 1;
        if (C.state == VC_FAULT && C.store[v].count) bad = 1;
    }
    if ((C.state == VC_IDLE || C.state == VC_FAULT) && C.armed_mask) bad = 1;
    if (bad) fprintf(stderr, "case %lu (%s): invariant broken (state %u)\n", i, what, C.state);
    return bad;
}

int main(int argc, char **argv)
{
    unsigned long n = argc > 1 ? strtoul(argv[1], 0, 10) : 200000ul, i, failed = 0;
    unsigned long unanswered = 0, errors_before;
    static uint8_t buf[4096], prog[8192];
    uint8_t seq = 0;
    uint32_t ms = 1000;
    rng_state = argc > 2 ? strtoull(argv[2], 0, 10) : 1u;
    vc_init(&C, VC_RESET_POWER);
    for (i = 0; i < n; i++) {
        unsigned kind = rn(10), len = 0, k;
        const char *what = "?";
        unsigned long before = tx_frames;
        int must_answer = 1;
        switch (kind) {
        case 0:                                              /* random bytes */
            what = "random bytes";
            len = 1 + rn(300);
            for (k = 0; k < len; k++) buf[k] = (uint8_t)rnd();
            break;
        case 1: case 2: {                                    /* damaged good frame */
            uint8_t p[64];
            unsigned pl = rn(30);
            for (k = 0; k < pl; k++) p[k] = (uint8_t)rnd();
            len = frame(buf, seq, (uint8_t)(1 + rn(0x30)), p, pl);
            if (kind == 1) { what = "bit flip"; k = rn(len); buf[k] ^= (uint8_t)(1u << rn(8)); }
            else { what = "cut"; len = 1 + rn(len - 1); }
            break;
        }
        case 3:                                              /* oversized */
            what = "oversize";
            buf[0] = 0xA5; buf[1] = 0x5A; buf[2] = (uint8_t)(241 + rn(15));
            len = 3 + rn(20);
            for (k = 3; k < len; k++) buf[k] = (uint8_t)rnd();
            break;
        case 4: case 5: case 6: {                            /* good frame, random content */
            static const uint8_t types[] = { VC_HELLO, VC_STATUS, VC_CONFIG, VC_PROG_BEGIN,
                VC_PROG_DATA, VC_PROG_VERIFY, VC_ARM, VC_ABORT, VC_TRIGGER, 0x44, 0x99 };
            uint8_t p[240], t = types[rn(sizeof types)];
            unsigned pl = rn(8) ? rn(12) : rn(241);
            for (k = 0; k < pl; k++) p[k] = (uint8_t)(rn(3) ? rn(4) : rnd());
            if (t == VC_HELLO && rn(2)) { memcpy(p, "RDY\x01", 4); pl = 4; }
            what = "random command";
            len = frame(buf, rn(6) ? seq : (uint8_t)rnd(), t, p, pl);
            if (buf[3] == seq || t == VC_HELLO) seq = (uint8_t)(buf[3] + 1);
            break;
        }
        case 7: {                                            /* a program, maybe damaged */
            uint8_t p[240], v = (uint8_t)rn(2);
            unsigned plen = program(prog), off;
            if (rn(2)) prog[rn(plen)] = (uint8_t)rnd();
            what = "program";
            p[0] = v; p[1] = (uint8_t)rn(2);
            memcpy(p + 2, &plen, 4);
            len = frame(buf, seq++, VC_PROG_BEGIN, p, 6);
            for (off = 0; off < plen && len < sizeof buf - 300; off += 235) {
                unsigned c = plen - off > 235 ? 235 : plen - off;
                p[0] = v; memcpy(p + 1, &off, 4); memcpy(p + 5, prog + off, c);
                len += frame(buf + len, seq++, VC_PROG_DATA, p, c + 5);
            }
            if (rn(2)) { p[0] = (uint8_t)(1u << v); len += frame(buf + len, seq++, VC_ARM, p, 1); }
            if (rn(2)) len += frame(buf + len, seq++, VC_TRIGGER, p, 0);
            break;
        }
        default:                                             /* ticks and trigger edges */
            what = "ticks";
            must_answer = 0;
            if (rn(4) == 0) vc_trigger_edge(&C);
            for (k = rn(200); k; k--) tick((int)rn(2));
            break;
        }
        errors_before = C.errors_sent;
        if (len) vc_rx(&C, buf, len, ms);
        ms += 60;                                            /* the byte timeout passes */
        vc_poll(&C, ms);
        (void)errors_before;
        if (must_answer && tx_frames == before) {
            unanswered++;
            fprintf(stderr, "case %lu (%s): nothing sent back\n", i, what);
        }
        if (check(i, what)) failed++;
        if (C.state != VC_PLAYING) {                         /* time passes: pulses end */
            now_us += 70000;
            if (board_outputs()) { failed++; fprintf(stderr, "case %lu (%s): valve open while not playing\n", i, what); }
        }
        if (rn(50) == 0) {                                   /* ABORT: every valve off */
            uint8_t f[8];
            vc_rx(&C, f, frame(f, seq++, VC_ABORT, 0, 0), ms);
            if (board_outputs() || C.state != VC_IDLE) { failed++; fprintf(stderr, "case %lu: ABORT left a valve open\n", i); }
        }
    }
    printf("fuzz_core: %lu cases, %lu frames sent back (%lu bytes), %lu pulses, %lu ticks "
           "interrupting the link, %lu unanswered\n", n, tx_frames, tx_bytes, pulses, isr_ticks,
           unanswered);
    if (lock_depth) { failed++; fprintf(stderr, "a lock left taken\n"); }
    printf("%lu passed, %lu failed\n", n - failed - unanswered, failed + unanswered);
    return failed + unanswered ? 1 : 0;
}
