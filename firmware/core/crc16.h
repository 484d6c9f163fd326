/* CRC-16/CCITT-FALSE: polynomial 0x1021, init 0xFFFF, no reflection, no final XOR
 * (check value 0x29B1 over "123456789"). PROTOCOL.md section 2. */
#ifndef VC_CRC16_H
#define VC_CRC16_H
#include <stddef.h>
#include <stdint.h>

#define VC_CRC_INIT 0xFFFFu
uint16_t vc_crc16_update(uint16_t crc, const uint8_t *data, size_t n);
uint16_t vc_crc16_byte(uint16_t crc, uint8_t b);
#endif
