/* The few LPC2148 registers this firmware uses (addresses from NXP UM10139, "LPC214x
 * User manual": system control, pin connect block, GPIO, UART0, Timer0, Timer1, watchdog, VIC). */
#ifndef LPC2148_H
#define LPC2148_H
#include <stdint.h>

#define REG(a) (*(volatile uint32_t *)(a))

/* system control block */
#define MAMCR     REG(0xE01FC000)
#define MAMTIM    REG(0xE01FC004)
#define PLLCON    REG(0xE01FC080)
#define PLLCFG    REG(0xE01FC084)
#define PLLSTAT   REG(0xE01FC088)
#define PLLFEED   REG(0xE01FC08C)
#define VPBDIV    REG(0xE01FC100)
#define RSIR      REG(0xE01FC180)   /* reset source: bit 0 POR, 1 EXTR, 2 WDTR, 3 BODR */

/* pin connect block */
#define PINSEL0   REG(0xE002C000)
#define PINSEL1   REG(0xE002C004)

/* GPIO port 0 (legacy, slow GPIO) */
#define IO0PIN    REG(0xE0028000)
#define IO0SET    REG(0xE0028004)
#define IO0DIR    REG(0xE0028008)
#define IO0CLR    REG(0xE002800C)

/* UART0 */
#define U0RBR     REG(0xE000C000)
#define U0THR     REG(0xE000C000)
#define U0DLL     REG(0xE000C000)
#define U0DLM     REG(0xE000C004)
#define U0IER     REG(0xE000C004)
#define U0IIR     REG(0xE000C008)
#define U0FCR     REG(0xE000C008)
#define U0LCR     REG(0xE000C00C)
#define U0LSR     REG(0xE000C014)
#define LSR_RDR   0x01u
#define LSR_THRE  0x20u

/* Timer0 */
#define T0IR      REG(0xE0004000)
#define T0TCR     REG(0xE0004004)
#define T0TC      REG(0xE0004008)
#define T0PR      REG(0xE000400C)
#define T0MCR     REG(0xE0004014)
#define T0MR0     REG(0xE0004018)
#define T0MR1     REG(0xE000401C)
#define T0MR2     REG(0xE0004020)

/* Timer1: the valves' match outputs (valves.h) */
#define T1TCR     REG(0xE0008004)
#define T1TC      REG(0xE0008008)
#define T1PR      REG(0xE000800C)
#define T1MCR     REG(0xE0008014)
#define T1MR0     REG(0xE0008018)
#define T1MR1     REG(0xE000801C)
#define T1EMR     REG(0xE000803C)   /* EM0/EM1 the outputs, EMC0/EMC1 their match action */

/* watchdog */
#define WDMOD     REG(0xE0000000)
#define WDTC      REG(0xE0000004)
#define WDFEED    REG(0xE0000008)

/* vectored interrupt controller */
#define VICIntSelect  REG(0xFFFFF00C)
#define VICIntEnable  REG(0xFFFFF010)
#define VICIntEnClr   REG(0xFFFFF014)
#define VICVectAddr   REG(0xFFFFF030)
#define VICDefVectAddr REG(0xFFFFF034)
#define VICVectAddr0  REG(0xFFFFF100)
#define VICVectAddr1  REG(0xFFFFF104)
#define VICVectCntl0  REG(0xFFFFF200)
#define VICVectCntl1  REG(0xFFFFF204)
#define VIC_TIMER0 4u
#define VIC_UART0  6u

#endif
