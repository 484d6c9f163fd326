/* The LPC2148 board's valve outputs (lpc2148/valves.h) against a model of Timer1's match
 * outputs, run by `make board-valves`. No board is needed: valves.h is included over a
 * simulated timer whose registers have the board's names. Every register access takes the
 * simulated clock forward by 1-12 PCLK cycles (48 per microsecond), and a match clears its
 * output as the counter reaches it, so over millions of random pulses the timer's matches
 * land between every pair of the code's register accesses (a read of EMR and the write
 * after it, a match register's write and the output's set).
 *
 * After every call and every idle stretch it checks: an open valve's end is still to come
 * (none stays open until the counter wraps, 71.6 minutes), and a valve whose pulse is not
 * over is open with its end within the microseconds its call took of the pulse's. The
 * same harness runs the pulse written as before, as a plain read-modify-write of EMR with
 * no closing of what is due, and fails unless the model catches that one: the check can
 * fail. Prints "board valves: ..." and exits non-zero on a failure. */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>

static struct {
    uint64_t cycles;           /* PCLK cycles; the counter is cycles / 48 (1 us) */
    uint32_t tc, emr, mr[2];
    unsigned long late_sets;   /* EMR writes that set an output whose end had come */
} hw;
static uint32_t rng = 12345u;

static uint32_t rnd(void)
{
    rng ^= rng << 13; rng ^= rng >> 17; rng ^= rng << 5;
    return rng;
}

static uint32_t counter(void) { return (uint32_t)(hw.cycles / 48u); }

/* Take the clock forward; each counter value reached clears the outputs matched there. */
static void run_cycles(uint64_t n)
{
    uint32_t before = counter(), after;
    unsigned v;
    hw.cycles += n;
    after = counter();
    for (v = 0; v < 2; v++) {
        uint32_t emc = (hw.emr >> (4 + 2 * v)) & 3u;
        if (emc == 1u && (uint32_t)(hw.mr[v] - before - 1u) < (uint32_t)(after - before))
            hw.emr &= ~(1u << v);
    }
    hw.tc = after;
}

/* Software's writes of EMR, seen at the next access (only software sets an output): count
 * those that set an output whose end had come. */
static uint32_t emr_seen;
static void note_writes(void)
{
    unsigned v;
    for (v = 0; v < 2; v++)
        if ((hw.emr & (1u << v)) && !(emr_seen & (1u << v)) && (int32_t)(hw.tc - hw.mr[v]) >= 0)
            hw.late_sets++;
    emr_seen = hw.emr;
}

static uint32_t *reg(uint32_t *r)
{
    note_writes();
    run_cycles(1u + rnd() % 12u);
    emr_seen = hw.emr;
    return r;
}

#define T1TC (*reg(&hw.tc))
#define T1MR0 (*reg(&hw.mr[0]))
#define T1MR1 (*reg(&hw.mr[1]))
#define T1EMR (*reg(&hw.emr))
#include "../lpc2148/valves.h"

static void pulse_fixed(unsigned v, uint16_t width)
{
    valves_pulse(v, width);
}

/* As the board did it before valves.h (with Timer1's outputs): EMR read, then written. */
static void pulse_plain(unsigned v, uint16_t width)
{
    uint32_t bit = 1u << v, emr = T1EMR, end = T1TC + width;
    if (!(emr & bit) || (int32_t)(end - valves_end(v)) > 0) valves_set_end(v, end);
    emr = T1EMR;
    T1EMR = emr | bit;
}

static uint16_t width_draw(void)
{
    switch (rnd() % 4u) {
    case 0: return (uint16_t)(1u + rnd() % 8u);            /* shorter than the code's steps */
    case 1: return (uint16_t)(400u + rnd() % 200u);        /* FM pulses */
    case 2: return (uint16_t)(1u + rnd() % 2000u);         /* PWM, ends near the next start */
    default: return (uint16_t)(1u + rnd() % 65535u);
    }
}

/* Pulses and idle stretches at random; returns the number of failed checks. */
static unsigned long run(void (*pulse)(unsigned, uint16_t), unsigned long steps, int quiet)
{
    uint32_t lo[2] = {0, 0}, hi[2] = {0, 0};   /* the end is between lo and hi */
    int active[2] = {0, 0};
    unsigned long fails = 0, i;
    hw.cycles = (uint64_t)(0xFFFFFF00u - 5000u) * 48u;        /* the counter wraps early */
    hw.tc = counter();
    hw.emr = VALVES_EMR_CLOSED;
    hw.mr[0] = hw.mr[1] = 0;
    hw.late_sets = 0;
    emr_seen = hw.emr;
    for (i = 0; i < steps; i++) {
        uint32_t r = rnd() % 100u, t0, t1, now;
        unsigned v;
        if (r < 70u) {
            uint16_t w = width_draw();
            v = rnd() % 2u;
            t0 = counter();
            pulse(v, w);
            t1 = counter();
            if (!active[v] || (int32_t)(t0 + w - lo[v]) > 0) lo[v] = t0 + w;
            if (!active[v] || (int32_t)(t1 + w - hi[v]) > 0) hi[v] = t1 + w;
            active[v] = 1;
        } else if (r < 73u) {
            valves_off();
            active[0] = active[1] = 0;
        } else {
            run_cycles((uint64_t)(rnd() % (r < 90u ? 48u * 20u : 48u * 3000u)));
        }
        note_writes();
        now = counter();
        for (v = 0; v < 2; v++) {
            int open = (hw.emr >> v) & 1u;
            if (active[v] && (int32_t)(now - hi[v]) >= 0) active[v] = 0;
            if (open && (int32_t)(hw.mr[v] - now) <= 0) {
                if (!quiet && fails < 5)
                    fprintf(stderr, "  step %lu: valve %u open, its end %u has come (now %u)\n",
                            i, v, (unsigned)hw.mr[v], (unsigned)now);
                fails++;
            } else if (active[v] && (int32_t)(lo[v] - now) > 0 &&
                       (!open || (int32_t)(hw.mr[v] - lo[v]) < 0 ||
                        (int32_t)(hi[v] - hw.mr[v]) < 0)) {
                if (!quiet && fails < 5)
                    fprintf(stderr, "  step %lu: valve %u open %d, end %u, wanted %u..%u\n",
                            i, v, open, (unsigned)hw.mr[v], (unsigned)lo[v], (unsigned)hi[v]);
                fails++;
            } else if (!active[v] && open) {
                if (!quiet && fails < 5)
                    fprintf(stderr, "  step %lu: valve %u open after its pulses\n", i, v);
                fails++;
            }
        }
    }
    return fails;
}

int main(int argc, char **argv)
{
    unsigned long steps = argc > 1 ? strtoul(argv[1], 0, 10) : 2000000ul;
    unsigned long fixed_fails, plain_fails, fixed_late;
    fixed_fails = run(pulse_fixed, steps, 0);
    fixed_late = hw.late_sets;
    plain_fails = run(pulse_plain, steps, 1);
    printf("board valves: %lu steps; valves.h %lu failed checks (%lu EMR writes set an output "
           "whose end had come; each closed before its call returned); the plain "
           "read-modify-write %lu failed checks\n", steps, fixed_fails, fixed_late, plain_fails);
    if (fixed_fails) return 1;
    if (!fixed_late) { fprintf(stderr, "the races were not reached: no check\n"); return 1; }
    if (!plain_fails) {
        fprintf(stderr, "the model let the plain write pass: no check\n");
        return 1;
    }
    return 0;
}
