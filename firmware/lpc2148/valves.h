/* The valve outputs on Timer1's external match outputs (PROTOCOL.md 9; thesis 2.3.1): valve
 * 0 on P0.12 (MAT1.0), valve 1 on P0.13 (MAT1.1). A pulse sets its valve's output (EMR's
 * EMn bit, written by software) and puts its end in MRn; at the match the timer clears the
 * output in hardware (EMCn = 01), so a valve closes on time whatever the software does.
 * Before, a Timer0 match interrupt closed it, and it waited while the main loop handled a
 * frame with interrupts off: up to ~0.67 ms for a PROG_DATA frame, a 500 us pulse open
 * more than twice as long for ~3 % of the pulses while a program streams (a review). The
 * main loop now keeps interrupts off ~10-15 us at most (core/valvectl.h, make rx-work).
 *
 * Included by board.c over the LPC2148's registers, and by tests/board_valves.c over a
 * simulated Timer1 behind the same names (T1TC, T1EMR, T1MR0, T1MR1). Call with
 * interrupts off. Every EMR update is a read and a write: the timer can clear a bit
 * between them, and the write puts it back, so each update ends by closing what is due
 * (valves_close_due). */
#ifndef VALVES_H
#define VALVES_H
#include <stdint.h>

#define VALVES_N 2u
#define VALVES_EM_MASK 0x3u                          /* EM0, EM1: the outputs */
#define VALVES_EMR_CLOSED ((1u << 4) | (1u << 6))    /* EMC0 = EMC1 = 01: clear on match */

static inline uint32_t valves_end(unsigned v)
{
    return v == 0 ? T1MR0 : T1MR1;
}

static inline void valves_set_end(unsigned v, uint32_t t)
{
    if (v == 0) T1MR0 = t;
    else T1MR1 = t;
}

/* Clear every output that is set although its end has come: a match missed while its
 * register was being set (a very short pulse; the next would come when the counter wraps,
 * 71.6 minutes on), or a bit an EMR write put back after the timer had cleared it. A pass
 * takes a few cycles and each end passes once, so this ends after a pass or two. */
static inline void valves_close_due(void)
{
    for (;;) {
        uint32_t emr = T1EMR, now = T1TC, due = 0;
        unsigned v;
        for (v = 0; v < VALVES_N; v++)
            if ((emr & (1u << v)) && (int32_t)(now - valves_end(v)) >= 0) due |= 1u << v;
        if (!due) return;
        T1EMR = emr & ~due;
    }
}

/* Open valve v now for width_us microseconds. An open valve keeps the later of its two
 * ends (a pulse that starts as the one before ends: PWM at full duty). */
static inline void valves_pulse(unsigned v, uint16_t width_us)
{
    uint32_t bit = 1u << v, emr, end;
    if (v >= VALVES_N) return;
    emr = T1EMR;
    end = T1TC + width_us;
    if (!(emr & bit) || (int32_t)(end - valves_end(v)) > 0) valves_set_end(v, end);
    emr = T1EMR;
    T1EMR = emr | bit;
    valves_close_due();
}

/* Close both valves at once (the match controls kept). */
static inline void valves_off(void)
{
    T1EMR = VALVES_EMR_CLOSED;
}

/* Bit v set while valve v is open. */
static inline uint8_t valves_open(void)
{
    return (uint8_t)(T1EMR & VALVES_EM_MASK);
}

#endif
