/* LPC2148 board layer (PROTOCOL.md 9; thesis 2.3.1): 12 MHz crystal, PLL to 48 MHz,
 * PCLK 48 MHz; UART0 115 200 8N1 (divisor 26: 115 385 baud, +0.16 %); Timer0 counting
 * microseconds, MR0 the 2 ms valve tick; valve outputs P0.12 (part) and P0.13 (scaffold)
 * as Timer1's match outputs MAT1.0 / MAT1.1, closed by the timer in hardware (valves.h);
 * trigger input P0.16 from the Adept C40, sampled every tick; 10 s watchdog fed by the main
 * loop while the tick runs. */
#include <stdint.h>
#include "lpc2148.h"
#include "../core/board.h"
#include "../core/valvectl.h"
#include "valves.h"

#define VALVE0 (1u << 12)                                    /* MAT1.0 */
#define VALVE1 (1u << 13)                                    /* MAT1.1 */
#define TRIGGER_PIN (1u << 16)
#define PCLK_HZ 48000000u
#define WDT_TICKS (PCLK_HZ / 4u * (VC_WATCHDOG_MS / 1000u))   /* WDT clock = PCLK / 4 */

static vc_core core;
static volatile uint8_t rx_ring[512];
static volatile uint16_t rx_head, rx_tail;
static volatile uint8_t tx_ring[1024];   /* written in interrupts, read by main */
static volatile uint16_t tx_head, tx_tail;
static volatile uint32_t now_ms;
static uint32_t trig_prev;

static inline uint32_t irq_save(void)
{
    uint32_t cpsr;
    __asm volatile("mrs %0, cpsr" : "=r"(cpsr));
    __asm volatile("msr cpsr_c, %0" : : "r"(cpsr | 0x80u) : "memory");
    return cpsr;
}

static inline void irq_restore(uint32_t cpsr)
{
    __asm volatile("msr cpsr_c, %0" : : "r"(cpsr) : "memory");
}

/* ------------------------------------------------------------------ board.h */

uint32_t board_lock(void) { return irq_save(); }
void board_unlock(uint32_t saved) { irq_restore(saved); }

/* From the tick interrupt and from the main loop with interrupts on: the room is taken
 * with them off, the bytes copied after (an interrupt's frame goes whole after ours; only
 * the main loop reads the queue, never while it is in here). */
void board_tx(const uint8_t *data, unsigned n)
{
    unsigned i, used;
    uint16_t at;
    uint32_t s = irq_save();
    used = (uint16_t)(tx_head - tx_tail) % sizeof tx_ring;
    if (n > sizeof tx_ring - 1u - used) { irq_restore(s); return; }   /* full: dropped */
    at = tx_head;
    tx_head = (uint16_t)((tx_head + n) % sizeof tx_ring);
    irq_restore(s);
    for (i = 0; i < n; i++) {
        tx_ring[at] = data[i];
        at = (uint16_t)((at + 1u) % sizeof tx_ring);
    }
}

void board_valve_pulse(unsigned valve, uint16_t width_us, uint32_t play_tick)
{
    (void)play_tick;
    valves_pulse(valve, width_us);
}

void board_valves_off(void)
{
    valves_off();
}

uint8_t board_outputs(void)
{
    return valves_open();
}

void board_note(int what, uint32_t a, uint32_t b) { (void)what; (void)a; (void)b; }

/* ------------------------------------------------------------------ interrupts */

void timer0_isr(void) __attribute__((interrupt("IRQ")));
void timer0_isr(void)
{
    uint32_t ir = T0IR;
    if (ir & 1u) {                                              /* MR0: the valve tick */
        uint32_t due = T0MR0, pin;
        unsigned n = 0;
        pin = IO0PIN & TRIGGER_PIN;
        if (pin && !trig_prev) vc_trigger_edge(&core);           /* rising edge */
        trig_prev = pin;
        for (;;) {
            T0IR = 1u;
            T0MR0 = due + VC_TICK_US;
            now_ms += VC_TICK_US / 1000u;
            vc_tick(&core, (T0TC - due) > VC_TICK_US);
            /* a tick that ran long (thousands of pulses on one tick) can end after the
             * next one was due: its match would then come only when the counter wraps,
             * 71.6 minutes on. Run the ticks already due now, late, as the host build
             * catches up; past 64 of them, start the ticks again from now. */
            if ((int32_t)(T0TC - T0MR0) < 0) break;
            due = T0MR0;
            if (++n >= 64u) {
                /* the ticks skipped here shift the play against the robot: they count as
                 * late ticks, which DONE and STATUS report (they went uncounted) */
                if (core.state == VC_PLAYING)
                    core.late_ticks += (T0TC - T0MR0) / VC_TICK_US + 1u;
                T0IR = 1u; T0MR0 = T0TC + VC_TICK_US; break;
            }
        }
    }
    VICVectAddr = 0;
}

/* An interrupt the VIC has no vector for (a spurious one): without a default address it
 * jumped to 0 and ran the start-up again without a reset (a review's finding). */
void spurious_isr(void) __attribute__((interrupt("IRQ")));
void spurious_isr(void)
{
    VICVectAddr = 0;
}

void uart0_isr(void) __attribute__((interrupt("IRQ")));
void uart0_isr(void)
{
    while (U0LSR & LSR_RDR) {
        uint8_t b = (uint8_t)U0RBR;
        uint16_t next = (uint16_t)((rx_head + 1u) % sizeof rx_ring);
        if (next != rx_tail) { rx_ring[rx_head] = b; rx_head = next; }
    }
    (void)U0IIR;
    VICVectAddr = 0;
}

/* ------------------------------------------------------------------ start-up */

static void feed_watchdog(void)
{
    uint32_t s = irq_save();
    WDFEED = 0xAA;
    WDFEED = 0x55;
    irq_restore(s);
}

static void clocks(void)
{
    PLLCFG = 0x23;                   /* M = 4 (MSEL 3), P = 2 (PSEL 1): 48 MHz, Fcco 192 MHz */
    PLLCON = 1;
    PLLFEED = 0xAA; PLLFEED = 0x55;
    while (!(PLLSTAT & (1u << 10))) { }                          /* PLOCK */
    PLLCON = 3;
    PLLFEED = 0xAA; PLLFEED = 0x55;
    MAMCR = 0; MAMTIM = 3; MAMCR = 2;                            /* flash accelerator */
    VPBDIV = 1;                                                  /* PCLK = CCLK */
}

int main(void)
{
    /* RSIR: POR bit 0, WDTR 2, BODR 3; a power-on sets BODR too, so a brown-out is BODR
     * without POR (it read "power-on": a supply dip mid-build looked like a fresh start) */
    uint32_t rsir = RSIR;
    uint8_t cause = (rsir & (1u << 2)) ? VC_RESET_WATCHDOG
        : ((rsir & (1u << 3)) && !(rsir & 1u)) ? VC_RESET_BROWNOUT : VC_RESET_POWER;
    uint32_t fed_ms;
    RSIR = 0x0F;
    clocks();
    PINSEL0 = (PINSEL0 & ~0x0Fu) | 0x05u;                        /* P0.0 TXD0, P0.1 RXD0 */
    PINSEL1 &= ~0x03u;                                           /* P0.16 GPIO */
    IO0CLR = VALVE0 | VALVE1;                  /* low as GPIO too (startup.S's hang) */
    IO0DIR = (IO0DIR | VALVE0 | VALVE1) & ~TRIGGER_PIN;
    T1TCR = 2;                                                   /* reset */
    T1PR = PCLK_HZ / 1000000u - 1u;                              /* 1 us per count */
    T1MCR = 0;                                                   /* matches only drive pins */
    valves_off();                                                /* outputs low, clear on match */
    T1TCR = 1;
    PINSEL0 = (PINSEL0 & ~(0x0Fu << 24)) | (0x0Au << 24);        /* P0.12 MAT1.0, P0.13 MAT1.1 */

    U0LCR = 0x83;                                                /* 8N1, divisor latch */
    U0DLL = PCLK_HZ / 16u / 115200u;                             /* 26 */
    U0DLM = 0;
    U0LCR = 0x03;
    U0FCR = 0x07;                                                /* FIFOs on and reset */
    U0IER = 0x01;                                                /* receive interrupt */

    vc_init(&core, cause);

    T0TCR = 2;                                                   /* reset */
    T0PR = PCLK_HZ / 1000000u - 1u;                              /* 1 us per count */
    T0MR0 = VC_TICK_US;
    T0MCR = 1;                                                   /* MR0 interrupt, no reset */
    T0TCR = 1;

    VICIntSelect = 0;
    VICDefVectAddr = (uint32_t)spurious_isr;
    VICVectAddr0 = (uint32_t)timer0_isr;
    VICVectCntl0 = 0x20u | VIC_TIMER0;
    VICVectAddr1 = (uint32_t)uart0_isr;
    VICVectCntl1 = 0x20u | VIC_UART0;
    VICIntEnable = (1u << VIC_TIMER0) | (1u << VIC_UART0);

    WDTC = WDT_TICKS;                                            /* thesis 2.3.1: 10 s */
    WDMOD = 0x03;                                                /* enable + reset */
    feed_watchdog();
    fed_ms = now_ms;
    irq_restore(irq_save() & ~0x80u);                            /* IRQs on */

    for (;;) {
        /* fed only while the tick runs: a loop fed regardless kept a board whose tick (and
         * with it the valves' closes) had stopped from the watchdog's reset */
        if (now_ms != fed_ms) {
            fed_ms = now_ms;
            feed_watchdog();
        }
        /* interrupts on: the core locks what the tick shares (core/valvectl.h); with all of
         * vc_rx locked a PROG_DATA frame held them off ~0.9 ms and start markers up to 28 ms,
         * delaying the tick and overrunning the UART's 16-byte FIFO */
        while (rx_tail != rx_head) {
            uint8_t b = rx_ring[rx_tail];
            rx_tail = (uint16_t)((rx_tail + 1u) % sizeof rx_ring);
            vc_rx(&core, &b, 1, now_ms);
        }
        vc_poll(&core, now_ms);
        while (tx_tail != tx_head && (U0LSR & LSR_THRE)) {
            unsigned k;
            for (k = 0; k < 16u && tx_tail != tx_head; k++) {    /* one FIFO's worth */
                U0THR = tx_ring[tx_tail];
                tx_tail = (uint16_t)((tx_tail + 1u) % sizeof tx_ring);
            }
        }
    }
}
